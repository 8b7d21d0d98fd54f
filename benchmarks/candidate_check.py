"""How well does the tracker's most likely candidate, checked by module correlation, name the
stickers that go to decoding? The study behind ``LocaliserConfig.check_expected`` and its
thresholds (``DecodeConfig.expected_min_score``, ``expected_min_margin``; README, Speed).

Replays each session with the localiser without that check (every detection it would see still
goes to decoding, as before the check was made). Every detection that goes to decoding while the
tracker has a pose is also, on the side, checked against the tracker's most likely candidate:
the rectified raster's data modules are correlated with that sticker's in each of the four
rotations (:func:`tagloc.vision.decode.verify_id`, the check a tracked sticker's re-verification
uses). The simulator's ground truth (``groundtruth_frames.jsonl``: the stickers in view, by frame
index) says which sticker the detection is. Nothing else the localiser does is changed.

Prints, for the events whose most likely candidate is the true sticker, the best rotation's score
and the other rotations' highest, and for the events whose candidate is wrong (another or an
unmapped sticker in view), the highest score over the four rotations: how far apart they lie,
and what share of true events a threshold would name.

``--swap-every N`` makes the hardest case: the localiser is given a map in which every N-th
sticker's ID is its decade neighbour's (the same first two data codewords, the last digit one
on), so where such a sticker is seen the tracker expects the neighbour: every one of those events
is a wrong candidate that differs from the true ID in one data codeword and the error correction.

Example::

    python benchmarks/candidate_check.py out/eval/standard/sessions/* out/eval/field/sessions/*
    python benchmarks/candidate_check.py out/eval/standard/sessions/* --swap-every 3
"""

from __future__ import annotations

import argparse
import dataclasses
import json
from pathlib import Path

import numpy as np
from tqdm import tqdm

import tagloc.pipeline.localiser as localiser_mod
from tagloc.core.stickermap import StickerMap
from tagloc.io.session import SessionReader
from tagloc.vision.decode import verify_id
from tagloc.vision.decode.grid import RASTER_PX
from tagloc.vision.rectify import rectify

_TRUTH_RADIUS_PX = 40.0  # a detection is the sticker in view whose true centre is this close


def _truth(session: Path) -> dict[int, list[tuple[int, np.ndarray]]]:
    out = {}
    with (session / "groundtruth_frames.jsonl").open(encoding="utf-8") as f:
        for line in f:
            rec = json.loads(line)
            out[int(rec["index"])] = [
                (int(v["id"]), np.mean(np.asarray(v["corners"], float), axis=0)) for v in rec.get("visible", [])
            ]
    return out


def _neighbour(sid: int) -> int:
    """The ID of ``sid``'s decade with the next last digit (wrapping within the decade)."""
    return sid - sid % 10 + (sid % 10 + 1) % 10


def swapped(smap: StickerMap, every: int) -> StickerMap:
    """``smap`` with every ``every``-th sticker's ID replaced by its decade neighbour's (where that ID is
    not in the map already)."""
    ids = smap.ids.copy()
    taken = set(map(int, ids))
    for row in range(0, len(ids), every):
        n = _neighbour(int(ids[row]))
        if n not in taken:
            taken.add(n)
            ids[row] = n
    return dataclasses.replace(smap, ids=ids)


def study(session: Path, swap_every: int = 0) -> list[dict]:
    """One record per detection decoded while tracking: true ID (None: no sticker within the radius),
    the most likely candidate, its four rotations' scores and what decoding named."""
    reader = SessionReader(session)
    truth = _truth(session)
    smap = swapped(reader.map, swap_every) if swap_every else reader.map
    loc = localiser_mod.Localiser(
        smap,
        reader.rig,
        config=localiser_mod.LocaliserConfig(check_expected=False),
        # A swapped map's identification references are made in memory, not cached beside the session's.
        map_path=None if swap_every else session / "map.csv",
    )
    events: list[dict] = []
    frame = {"index": -1}
    decode_gated = loc._decode_gated

    def observed(gray, det, rig_cam, camera, t, timer):
        read, age = decode_gated(gray, det, rig_cam, camera, t, timer)
        cands = loc._candidates(det, rig_cam, timer)
        if cands:
            rect = rectify(gray, det, rig_cam.camera, RASTER_PX)
            c = det.outer.mean(axis=0)
            near = [sid for sid, cc in truth.get(frame["index"], []) if np.hypot(*(cc - c)) < _TRUTH_RADIUS_PX]
            events.append(
                {
                    "true": near[0] if near else None,
                    "candidate": cands[0],
                    "all": [float(verify_id(rect, cands[0], r, search_px=4)) for r in range(4)],
                    "distinct": [float(verify_id(rect, cands[0], r, search_px=4, distinct=True)) for r in range(4)],
                    "decoded": read.identity is not None,
                }
            )
        return read, age

    loc._decode_gated = observed
    for f in tqdm(reader.frames(), desc=session.name, unit="frame", leave=False):
        frame["index"] = f.index
        loc.process(f)
    return events


def report(events: list[dict]) -> None:
    """Print the score distributions of ``events`` (their ``scores``) and the threshold table."""
    right = [e for e in events if e["true"] is not None and e["true"] == e["candidate"]]
    wrong = [e for e in events if e["true"] is not None and e["true"] != e["candidate"]]
    unknown = [e for e in events if e["true"] is None]
    best = np.array([max(e["scores"]) for e in right])
    others = np.array([sorted(e["scores"])[-2] for e in right])
    wrong_max = np.array([max(e["scores"]) for e in wrong])
    print(f"  candidate is the true sticker:  {len(right)}")
    if len(right):
        q = np.percentile(best, [5, 25, 50, 75])
        print(f"    best rotation's score, 5/25/50/75 %: {q[0]:.2f} / {q[1]:.2f} / {q[2]:.2f} / {q[3]:.2f}")
        print(f"    the other rotations' highest: {others.max():.2f} (99 %: {np.percentile(others, 99):.2f})")
        undecoded = [max(e["scores"]) for e in right if not e["decoded"]]
        print(f"    decoding named nothing in {len(undecoded)} of them")
    pairs = len({(e["true"], e["candidate"]) for e in wrong})
    top = wrong_max.max() if len(wrong) else float("nan")
    print(f"  candidate is another sticker:   {len(wrong)} ({pairs} distinct pairs), highest score {top:.2f}")
    near = np.array([max(e["scores"]) for e in wrong if _neighbour(e["true"]) == e["candidate"]])
    if len(near):
        q = np.percentile(near, [50, 99])
        print(f"    its decade neighbour: {len(near)}, median {q[0]:.2f}, 99 % {q[1]:.2f}, highest {near.max():.2f}")
    print(f"  no sticker within {_TRUTH_RADIUS_PX:.0f} px in the truth: {len(unknown)}")
    print("  threshold  true events named  wrong events named")
    for th in (0.3, 0.35, 0.4, 0.45, 0.5, 0.6, 0.7):
        named = float(np.mean(best >= th)) if len(best) else float("nan")
        print(f"  {th:9.2f}  {named:16.2f}  {int(np.sum(wrong_max >= th)):18d}")


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("sessions", type=Path, nargs="+", help="simulated sessions (with groundtruth_frames.jsonl)")
    p.add_argument(
        "--swap-every", type=int, default=0, metavar="N", help="give every N-th sticker its decade neighbour's ID"
    )
    args = p.parse_args(argv)
    events = [e for s in args.sessions for e in study(s, args.swap_every)]
    print(f"{len(events)} detections decoded while tracking, {len(args.sessions)} sessions")
    for key, what in (
        ("all", "all 256 data modules"),
        ("distinct", "the modules a decade does not share"),
        ("both", "both, the lower of the two (the check needs both)"),
    ):
        print(f"\nscored on {what}:")
        report(
            [dict(e, scores=e[key] if key != "both" else np.minimum(e["all"], e["distinct"]).tolist()) for e in events]
        )
    return 0


if __name__ == "__main__":
    from tagloc.cli import run_guarded

    raise SystemExit(run_guarded("candidate_check.py", main))
