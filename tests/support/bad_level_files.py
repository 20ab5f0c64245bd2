"""Files that are not level files (non-UTF-8 text, random bytes, a PNG, empty, cut short, a folder, UTF-16), written
for the tests of every layer that reads level files: the loader, level sets, `learner.run` and `impulse levels`.

Each case comes with the parts its error message must hold, besides the file's path.
"""

from __future__ import annotations

import functools
import json
from pathlib import Path

import jax
import numpy as np

from impulse.engine.levels.kinetix_json import level_to_json_dict
from impulse.engine.levels.level import level_from_scene
from impulse.engine.physics.building import empty_scene
from impulse.engine.physics.sizes import SIZE_S

_PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
_CUT_AFTER = '": '  # the end of a key, before its value


@functools.cache
def good_level_text() -> str:
    """A valid level file's text (an empty S scene), written with indentation so that it spans many lines."""
    level = jax.tree.map(np.asarray, level_from_scene(jax.jit(empty_scene, static_argnums=0)(SIZE_S)))
    return json.dumps(level_to_json_dict(level, SIZE_S), indent=1)


def truncation_point(text: str) -> tuple[int, int, int]:
    """(offset, line, column) where `write_bad_inputs` cuts a level file: just after the first key past the
    middle, so json reports "Expecting value" exactly there."""
    cut = text.index(_CUT_AFTER, len(text) // 2) + len(_CUT_AFTER)
    line = text.count("\n", 0, cut) + 1
    column = cut - (text.rfind("\n", 0, cut) + 1) + 1
    return cut, line, column


def write_bad_inputs(folder: Path) -> dict[str, tuple[Path, list[str]]]:
    """Write one bad input per case into `folder`: {case: (path, parts the error message must contain)}."""
    folder.mkdir(parents=True, exist_ok=True)
    text = good_level_text()
    cut, line, column = truncation_point(text)
    random_bytes = np.random.default_rng(0).bytes(512)
    contents = {
        "latin-1 text": (b'{"name": "caf\xe9"}', ["not a UTF-8 text file (byte 0xe9 at offset 13)", "level file?"]),
        "random bytes": (random_bytes, ["not a UTF-8 text file (byte 0x", "is it a level file?"]),
        "PNG image": (_PNG_MAGIC + random_bytes, ["(byte 0x89 at offset 0)", "looks like a PNG image, not a level"]),
        "empty file": (b"", ["empty file"]),
        "blank file": (b" \n\t\n", ["only blank space"]),
        "truncated JSON": (
            text[:cut].encode(), ["not valid JSON", f"line {line} column {column}", "cut short"]
        ),
        "UTF-16 text": (text.encode("utf-16"), ["not a UTF-8 text file", "UTF-16", "save it as UTF-8"]),
    }
    written = {}
    for case, (data, expected) in contents.items():
        path = folder / f"{case.replace(' ', '_')}.json"
        path.write_bytes(data)
        written[case] = (path, expected)
    directory = folder / "a_folder.json"
    directory.mkdir(exist_ok=True)
    written["folder"] = (directory, ["is a folder, not a level file"])
    return written
