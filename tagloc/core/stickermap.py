"""Sticker maps: CSV ``id,x_m,y_m,yaw_deg[,sigma_m][,sigma_deg]`` with a header, validated, with a KD-tree index.

The optional survey columns give each sticker's position (per axis, m) and yaw (degrees) standard
deviation; an empty cell or a missing column means "not stated", left to the localiser's default.
A malformed map is refused before any work starts, with one line naming the file and line.
"""

from __future__ import annotations

import csv
import math
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from tagloc.core.errors import MapError
from tagloc.core.geometry import planar_T
from tagloc.core.sticker import MAX_ID, SIZE_M

HEADER = ["id", "x_m", "y_m", "yaw_deg"]
SIGMA_COLUMNS = ["sigma_m", "sigma_deg"]  # optional, after HEADER, in either order
# Largest |coordinate| accepted, m. A site spans kilometres at most; 100 km keeps float32 (which
# OpenCV uses inside) at better than a centimetre and keeps the KD-tree's arithmetic finite.
MAX_COORD_M = 1e5
# Largest |yaw| accepted, degrees. Any real heading is within one turn; a million degrees is a typo
# or a unit mix-up, and far beyond it (1e300) a float holds no angle at all (its spacing is 1e284).
MAX_YAW_DEG = 1e6

# The one rule for numbers in tagloc's text files (map.csv, frames.csv) and sticker ID arguments:
# plain ASCII decimals. Python's float() and int() also take "1_0" (as 10) and any Unicode digit
# ("\u0661" as 1), which a survey or a clock never writes: such a cell is a typo to refuse, not a
# number to guess. The words nan and inf pass, so that they are refused as "must be finite".
_DECIMAL = re.compile(r"[+-]?(?:(?:[0-9]+(?:\.[0-9]*)?|\.[0-9]+)(?:[eE][+-]?[0-9]+)?|nan|inf|infinity)", re.IGNORECASE)
_INTEGER = re.compile(r"[+-]?[0-9]+")
_BLANK = " \t\r\n"  # ASCII white space only, for the same reason
# A whole number of more digits than this comes back saturated: int() refuses 4300 digits and more,
# and every caller's range ends long before.
_MAX_DIGITS = 30
# Input text echoed in a message is clipped to this many characters: a 5000-digit cell or a line of
# 4096 NUL bytes must still make a one-line message.
SHOWN_CHARS = 40


def decimal_number(text: str) -> float | None:
    """``text`` as a float if it is a plain ASCII decimal (sign, digits, point, exponent; nan and inf
    included), else None. Surrounding ASCII blanks are ignored."""
    text = text.strip(_BLANK)
    return float(text) if _DECIMAL.fullmatch(text) else None


def decimal_integer(text: str) -> int | None:
    """``text`` as an int if it is a plain ASCII whole number (optional sign, digits 0-9), else None.
    Beyond ``_MAX_DIGITS`` significant digits the value saturates at +-10**30."""
    text = text.strip(_BLANK)
    if text.isascii() and text.isdigit() and len(text) <= _MAX_DIGITS:
        return int(text)  # the common case, without the pattern: frames.csv has a line per frame
    if not _INTEGER.fullmatch(text):
        return None
    digits = text.lstrip("+-").lstrip("0")
    value = int(digits or "0") if len(digits) <= _MAX_DIGITS else 10**_MAX_DIGITS
    return -value if text.startswith("-") else value


def shown(text: str) -> str:
    """``text`` quoted for a message, clipped to its first ``SHOWN_CHARS`` characters (with its
    length) when longer, so that bad input cannot make a message of unbounded length."""
    if len(text) <= SHOWN_CHARS:
        return repr(text)
    return f"{text[:SHOWN_CHARS]!r}... ({len(text)} characters)"


@dataclass
class StickerMap:
    """Stickers on the warehouse floor.

    Attributes:
        ids: (N,) int64 sticker IDs.
        xy: (N, 2) sticker centres in the world frame, metres.
        yaw: (N,) heading of each sticker's +x axis, radians CCW from world +x.
        source: the file it came from, for messages.
        sigma_xy: (N,) survey standard deviation of each centre, per axis, m; NaN where not stated.
        sigma_yaw: (N,) survey standard deviation of each yaw, rad; NaN where not stated.
    """

    ids: np.ndarray
    xy: np.ndarray
    yaw: np.ndarray
    source: str = "<memory>"
    sigma_xy: np.ndarray | None = None
    sigma_yaw: np.ndarray | None = None
    _tree: cKDTree = field(init=False, repr=False)
    _row: dict[int, int] = field(init=False, repr=False)

    def __post_init__(self) -> None:
        self.ids = np.asarray(self.ids, np.int64).ravel()
        self.xy = np.asarray(self.xy, float).reshape(-1, 2)
        self.yaw = np.asarray(self.yaw, float).ravel()
        n = len(self.ids)
        self.sigma_xy = np.full(n, np.nan) if self.sigma_xy is None else np.asarray(self.sigma_xy, float).ravel()
        self.sigma_yaw = np.full(n, np.nan) if self.sigma_yaw is None else np.asarray(self.sigma_yaw, float).ravel()
        self._tree = cKDTree(self.xy if len(self.xy) else np.zeros((0, 2)))
        self._row = {int(i): k for k, i in enumerate(self.ids)}

    def __len__(self) -> int:
        return len(self.ids)

    def __contains__(self, sticker_id: int) -> bool:
        return int(sticker_id) in self._row

    def row(self, sticker_id: int) -> int:
        """Row index of ``sticker_id``; KeyError if absent."""
        return self._row[int(sticker_id)]

    def T_world_sticker(self, sticker_id: int) -> np.ndarray:
        """Pose (4, 4) of a sticker's frame in the world."""
        k = self._row[int(sticker_id)]
        return planar_T(self.xy[k, 0], self.xy[k, 1], self.yaw[k])

    def within(self, x: float, y: float, radius: float) -> np.ndarray:
        """Row indices of stickers whose centre is within ``radius`` m of (x, y), nearest first."""
        rows = self._tree.query_ball_point((x, y), radius)
        if not rows:
            return np.zeros(0, np.int64)
        rows = np.asarray(rows, np.int64)
        d = np.hypot(*(self.xy[rows] - (x, y)).T)
        return rows[np.argsort(d, kind="stable")]

    def in_polygon(self, polygon: np.ndarray) -> np.ndarray:
        """Row indices of stickers whose centre lies inside ``polygon`` ((M, 2) floor vertices, m)."""
        from matplotlib.path import Path as MplPath

        polygon = np.asarray(polygon, float).reshape(-1, 2)
        centre = polygon.mean(axis=0)
        radius = float(np.max(np.hypot(*(polygon - centre).T)))
        rows = self._tree.query_ball_point(centre, radius)
        if not rows:
            return np.zeros(0, np.int64)
        rows = np.sort(np.asarray(rows, np.int64))
        inside = MplPath(polygon).contains_points(self.xy[rows])
        return rows[inside]

    @property
    def bounds(self) -> tuple[float, float, float, float]:
        """(xmin, ymin, xmax, ymax) of the sticker centres."""
        lo, hi = self.xy.min(axis=0), self.xy.max(axis=0)
        return float(lo[0]), float(lo[1]), float(hi[0]), float(hi[1])


def _number(text: str, where: str, column: str) -> float:
    """A cell's number; NaN and inf written as such are refused here. Digits too many for a float
    come back as inf, refused by each column's range with the range in the message."""
    value = decimal_number(text)
    if value is None:
        raise MapError(f"{where}: {column} {shown(text)} is not a number")
    if math.isnan(value) or (math.isinf(value) and any(c in "nNiI" for c in text)):
        raise MapError(f"{where}: {column} is {shown(text)} (must be finite)")
    return value


def _coord(text: str, where: str, column: str) -> float:
    value = _number(text, where, column)
    if abs(value) > MAX_COORD_M:
        raise MapError(f"{where}: {column} {shown(text.strip())} is beyond +-{MAX_COORD_M:g} m")
    return value


def _yaw(text: str, where: str) -> float:
    value = _number(text, where, "yaw_deg")
    if abs(value) > MAX_YAW_DEG:
        raise MapError(f"{where}: yaw_deg {shown(text.strip())} is beyond +-{MAX_YAW_DEG:g} degrees")
    return math.radians(value)


# Largest survey sigmas a map may state: beyond them a sticker's place or turn is not surveyed at all
# (and a sigma squared must stay a finite float).
MAX_SIGMA = {"sigma_m": 10.0, "sigma_deg": 180.0}


def _sigma(text: str, where: str, column: str) -> float:
    if not text.strip():
        return math.nan
    value = _number(text, where, column)
    if value < 0:
        raise MapError(f"{where}: {column} {shown(text.strip())} is negative")
    if value > MAX_SIGMA[column]:
        raise MapError(f"{where}: {column} {shown(text.strip())} is more than {MAX_SIGMA[column]:g}")
    return value


def load_map(path: str | Path, min_spacing_m: float = SIZE_M) -> StickerMap:
    """Load and validate a map CSV. Raises :class:`MapError` naming file and line on bad input.

    Refused: a wrong header, missing or extra columns, non-numbers (only plain ASCII decimals are
    numbers: :func:`decimal_number`), NaN or inf, coordinates beyond ``MAX_COORD_M``, a yaw beyond
    ``MAX_YAW_DEG``, IDs that are not
    integers in 0-99999, duplicate IDs, two stickers closer than ``min_spacing_m`` (default: one
    sticker width, so they would overlap), and an empty map.
    """
    path = Path(path)
    try:
        handle = path.open(newline="", encoding="utf-8-sig")  # -sig: a spreadsheet's byte-order mark is fine
    except OSError as exc:
        raise MapError(f"{path}: cannot read map ({exc.strerror})") from exc
    ids, xy, yaw, sig_m, sig_deg, lines = [], [], [], [], [], []
    seen: dict[int, int] = {}
    with handle:
        reader = csv.reader(handle)
        try:
            header = next(reader, None)
            if header is None:
                raise MapError(f"{path}: empty file, want header {','.join(HEADER)}")
            names = [h.strip() for h in header]
            extra = names[len(HEADER) :]
            if names[: len(HEADER)] != HEADER or len(set(extra)) != len(extra) or not set(extra) <= set(SIGMA_COLUMNS):
                raise MapError(
                    f"{path}:1: header is {shown(','.join(header))}, want {','.join(HEADER)}"
                    f" optionally followed by {' and/or '.join(SIGMA_COLUMNS)}"
                )
            ncol = len(names)
            for row in reader:
                line = reader.line_num
                where = f"{path}:{line}"
                if not row or (len(row) == 1 and not row[0].strip()):
                    continue
                if len(row) != ncol:
                    raise MapError(f"{where}: {len(row)} columns, want {ncol} ({','.join(names)})")
                id_value = _number(row[0], where, "id")
                if not 0 <= id_value <= MAX_ID or id_value != int(id_value):
                    raise MapError(f"{where}: id {shown(row[0].strip())} is not an integer in 0-{MAX_ID}")
                sid = int(id_value)
                if sid in seen:
                    raise MapError(f"{where}: duplicate id {sid} (first on line {seen[sid]})")
                seen[sid] = line
                ids.append(sid)
                xy.append((_coord(row[1], where, "x_m"), _coord(row[2], where, "y_m")))
                yaw.append(_yaw(row[3], where))
                sigmas = {c: _sigma(row[len(HEADER) + k], where, c) for k, c in enumerate(extra)}
                sig_m.append(sigmas.get("sigma_m", math.nan))
                sig_deg.append(sigmas.get("sigma_deg", math.nan))
                lines.append(line)
        except csv.Error as exc:
            raise MapError(f"{path}:{reader.line_num}: {exc}") from exc
        except UnicodeDecodeError as exc:
            raise MapError(f"{path}: not UTF-8 text") from exc
    if not ids:
        raise MapError(f"{path}: no stickers")
    smap = StickerMap(np.array(ids), np.array(xy), np.array(yaw), str(path), np.array(sig_m), np.radians(sig_deg))
    pairs = smap._tree.query_pairs(min_spacing_m, output_type="ndarray")
    if len(pairs):
        a, b = sorted(pairs[0])
        dist = float(np.hypot(*(smap.xy[a] - smap.xy[b])))
        raise MapError(
            f"{path}:{lines[b]}: sticker {ids[b]} is {dist:.3f} m from sticker {ids[a]} (line {lines[a]}),"
            f" closer than {min_spacing_m:.3f} m"
        )
    return smap


def save_map(smap: StickerMap, path: str | Path) -> None:
    """Write a map CSV (0.1 mm on positions, 0.001 degree on yaw); the sigma columns only when some
    are stated, rounded up to those steps."""
    with_sigma = bool(np.isfinite(smap.sigma_xy).any() or np.isfinite(smap.sigma_yaw).any())

    def cell(v: float, decimals: int) -> str:
        # Rounded up, never down: a sigma written sharper than it is (a tiny one as 0, an exact map)
        # would make the tracker trust the sticker more than its survey allows. The 1e-6 keeps a
        # value already on the grid (0.015 as 150.00000000000003e-4) where it is.
        if not math.isfinite(v):
            return ""
        return f"{math.ceil(v * 10**decimals - 1e-6) / 10**decimals:.{decimals}f}"

    with Path(path).open("w", newline="", encoding="utf-8") as f:
        w = csv.writer(f)
        w.writerow(HEADER + (SIGMA_COLUMNS if with_sigma else []))
        for k, (sid, (x, y), a) in enumerate(zip(smap.ids, smap.xy, smap.yaw)):
            row = [int(sid), f"{x:.4f}", f"{y:.4f}", f"{math.degrees(a):.3f}"]
            if with_sigma:
                row += [cell(float(smap.sigma_xy[k]), 4), cell(math.degrees(float(smap.sigma_yaw[k])), 3)]
            w.writerow(row)
