"""Reading a JSON file the user gave, every way it can be wrong turned into one line naming the file;
writing one as standard JSON (null for a figure that is not a number)."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

from tagloc.core.errors import InputError


class DuplicateKey(ValueError):
    """An object of the file names ``key`` twice; its text is the message's, after the file's name."""

    def __init__(self, key: str) -> None:
        super().__init__(f"key {json.dumps(key)[:60]} appears twice in one object")
        self.key = key


def unique_keys(pairs: list[tuple[str, object]]) -> dict:
    """An object's members as a dict, refusing a key given twice (``json`` keeps the last silently):
    ``object_pairs_hook`` of ``json.loads``, raising :class:`DuplicateKey`."""
    out: dict = {}
    for key, value in pairs:
        if key in out:
            raise DuplicateKey(key)
        out[key] = value
    return out


def read_json(path: Path, error: type[InputError], what: str = "") -> object:
    """The parsed contents of ``path``; ``error`` (naming the file, and the line for bad JSON) if it
    cannot be read, is not UTF-8 text, is not valid JSON, names a key twice in one object, is nested
    too deeply to parse or holds an integer too long for Python to convert. A UTF-8 byte-order mark
    (an editor's) is fine, as in the CSV files.
    ``what`` names the file's kind in the "cannot read" message (e.g. "rig")."""
    try:
        return json.loads(path.read_bytes().decode("utf-8-sig"), object_pairs_hook=unique_keys)
    except DuplicateKey as exc:
        raise error(f"{path}: {exc}") from None
    except OSError as exc:
        raise error(f"{path}: cannot read{' ' + what if what else ''} ({exc.strerror})") from None
    except UnicodeDecodeError as exc:
        raise error(f"{path}: not a text file (byte {exc.start} is not UTF-8)") from None
    except json.JSONDecodeError as exc:
        raise error(f"{path}: line {exc.lineno}: not valid JSON ({exc.msg})") from None
    except RecursionError:
        raise error(f"{path}: JSON nested too deeply") from None
    except ValueError as exc:
        # Valid JSON that Python refuses to convert: an integer beyond its digit limit (4300 by default).
        raise error(f"{path}: not usable JSON ({str(exc).split(':')[0]})") from None


def write_json(path: Path, doc: object) -> None:
    """Write ``doc`` as standard JSON: numpy numbers as plain ones, and NaN or infinite figures (a
    walk with nothing scored, a run too short for NEES bounds) as null, which JSON has for them
    (Python's NaN token is refused by strict parsers: JavaScript's, Go's, Rust's serde_json)."""
    path.write_text(json.dumps(_json_ready(doc), indent=1, allow_nan=False) + "\n", encoding="utf-8")


def _json_ready(value: object) -> object:
    if isinstance(value, dict):
        return {k: _json_ready(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_json_ready(v) for v in value]
    if isinstance(value, (np.floating, np.integer, np.bool_)):
        value = value.item()
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value
