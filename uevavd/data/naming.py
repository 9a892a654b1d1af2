"""Parse UEVAVD scene-folder names and view file names, canonical or variant.

The real release names an image "UAV coordinates + target name + scene id" without
documenting separators, signs, padding or spelling. :func:`parse_view_stem` accepts:

* separators ``_``, ``-`` or spaces (``-`` is a sign when it starts the name, follows an
  axis letter or another ``-``, or when the name also uses ``_``/space as separator);
* coordinate tokens with or without axis letters (``x-50``, ``X=-50``, ``-50``), signs
  optional for positives, zero padding or none; with axis letters any order, without
  them x, y, z in that order;
* the target in any case with ``_``/``-``/space inside ("SportsCar", "Sports_Car",
  "sports car", "SUV") and a few aliases ("pick-up truck", "sport car");
* the scene id after the target (``_001``, ``_12``, ``_scene_3``, ``_train_605``) or
  before the coordinates, or absent (then the folder decides).

:func:`parse_scene_dir` accepts ``001``, ``1``, ``scene_001``, ``context-1``, ``00`` and
``train_605``. Both raise :class:`NameParseError` (a ``ValueError``) saying what was
expected.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

from .splits import CLASSIFIER_SCENE, N_CONTEXTS, TARGETS, UNOCCLUDED_SCENE

#: Image extensions the reader accepts (compared lower-case).
IMAGE_EXTS: tuple[str, ...] = (".png", ".jpg", ".jpeg")

#: Spellings (lower-case, letters only) mapped to canonical target names.
TARGET_ALIASES: dict[str, str] = {
    **{t: t for t in TARGETS},
    "hatch": "hatchback",
    "pickuptruck": "pickup",
    "pickups": "pickup",
    "sportcar": "sportscar",
    "sportscars": "sportscar",
    "sports": "sportscar",
    "sedans": "sedan",
    "saloon": "sedan",
    "sportutilityvehicle": "suv",
    "suvs": "suv",
}

# Words that may label the scene id inside a file or folder name ("scene_3", "ctx-12").
_SCENE_WORDS = ("scene", "context", "ctx", "sc", "c")
_SCENE_DIR = re.compile(r"^(?:(?:scene|context|ctx|sc|c)[\s_-]*)?(\d+)$", re.IGNORECASE)
_CLASSIFIER_DIR = re.compile(r"^train[\s_-]*605$", re.IGNORECASE)
_CLASSIFIER_SUFFIX = re.compile(r"(?:^|[\s_-])train[\s_-]*605$", re.IGNORECASE)
_COORD = re.compile(r"^(?:([xyz])\s*[=:]?\s*)?([+-]?\d+)$", re.IGNORECASE)
_COMPACT = re.compile(r"([xyz])\s*[=:]?\s*([+-]?\d+)", re.IGNORECASE)
_WORD = re.compile(r"^[a-z]+$", re.IGNORECASE)

CANONICAL_HINT = "expected e.g. 'x-50_y+40_z080_sedan_001' (coordinates, target, scene id)"


class NameParseError(ValueError):
    """A scene-folder or view file name that cannot be parsed; the message says why."""


class UnknownTargetError(NameParseError):
    """A name whose target word is none of the five classes."""


@dataclass(frozen=True)
class SceneId:
    """A parsed scene folder: ``kind`` is "context", "unoccluded" or "classifier"."""

    name: str
    kind: str
    context: int | None

    @property
    def sort_key(self) -> tuple[int, int, str]:
        order = {"context": 0, "unoccluded": 1, "classifier": 2}[self.kind]
        return (order, self.context or 0, self.name)


@dataclass(frozen=True)
class ParsedName:
    """A parsed view file stem: grid coordinates in metres, canonical target, and the
    scene id written in the name (``None`` when the name carries none)."""

    xyz: tuple[int, int, int]
    target: str
    scene: str | None


def normalize_target(name: str) -> str:
    """Canonical target name (one of ``splits.TARGETS``) for a spelling variant.

    Case, ``_``, ``-``, spaces and other non-letters are ignored: "Sports_Car",
    "sports car" and "SportsCar" all give "sportscar". Raises :class:`NameParseError`.
    """
    key = re.sub(r"[^a-z]", "", str(name).lower())
    if key in TARGET_ALIASES:
        return TARGET_ALIASES[key]
    raise UnknownTargetError(f"unknown target {name!r}: expected one of {list(TARGETS)} (any case/separators)")


def parse_scene_dir(name: str) -> SceneId:
    """Parse a scene folder name: "001"/"1"/"scene_001"/"context-1" -> context 1,
    "00"/"0" -> the unoccluded scene, "train_605" -> the classifier scene."""
    if _CLASSIFIER_DIR.match(name):
        return SceneId(name, "classifier", None)
    m = _SCENE_DIR.match(name.strip())
    if not m:
        raise NameParseError(
            f"folder name {name!r} is not a scene: expected a context id 1..{N_CONTEXTS} "
            f"('001', '1', 'scene_001'), {UNOCCLUDED_SCENE!r} or {CLASSIFIER_SCENE!r}"
        )
    number = int(m.group(1))
    if number == 0:
        return SceneId(name, "unoccluded", None)
    if number > N_CONTEXTS:
        raise NameParseError(f"folder name {name!r}: context id {number} is out of range 1..{N_CONTEXTS}")
    return SceneId(name, "context", number)


def scene_matches(token: str, scene: SceneId) -> bool:
    """Whether a scene id written in a file name (e.g. "12", "012", "train_605") names
    the folder's scene."""
    if _CLASSIFIER_DIR.match(token):
        return scene.kind == "classifier"
    if token.isdigit():
        number = int(token)
        return (scene.kind == "unoccluded" and number == 0) or scene.context == number
    return False


def _split_tokens(stem: str) -> list[str]:
    """Split a stem into tokens, deciding for each ``-`` whether it is a sign."""
    dash_is_separator = "_" not in stem and not re.search(r"\s", stem)
    if not dash_is_separator:
        return [t for t in re.split(r"[\s_]+|-(?!\d)", stem) if t]
    chars = []
    for i, ch in enumerate(stem):
        if ch == "-":
            nxt = stem[i + 1] if i + 1 < len(stem) else ""
            prev = stem[i - 1] if i else ""
            prev_is_axis = prev.lower() in "xyz" and (i < 2 or not stem[i - 2].isalpha()) if prev else False
            is_sign = nxt.isdigit() and (i == 0 or prev == "-" or prev_is_axis)
            chars.append("-" if is_sign else " ")
        else:
            chars.append(ch)
    return [t for t in "".join(chars).split() if t]


def parse_view_stem(stem: str) -> ParsedName:
    """Parse a view file stem (file name without extension). See the module docstring
    for the accepted variants. Raises :class:`NameParseError` saying what was expected.
    """
    scene: str | None = None
    rest = stem.strip()
    m = _CLASSIFIER_SUFFIX.search(rest)
    if m:
        scene, rest = CLASSIFIER_SCENE, rest[: m.start()]
    # kinds: ("c", axis, value) coordinate/number, ("w", word)
    items: list[tuple] = []
    for tok in _split_tokens(rest):
        cm = _COORD.match(tok)
        if cm:
            items.append(("c", (cm.group(1) or "").lower(), int(cm.group(2))))
        elif _WORD.match(tok):
            items.append(("w", tok))
        elif _COMPACT.fullmatch(tok) or re.fullmatch(r"(?:[xyz]\s*[=:]?\s*[+-]?\d+)+", tok, re.IGNORECASE):
            items.extend(("c", a.lower(), int(v)) for a, v in _COMPACT.findall(tok))
        else:
            raise NameParseError(f"cannot parse token {tok!r} in {stem!r}: {CANONICAL_HINT}")
    words = [i for i, it in enumerate(items) if it[0] == "w"]
    if not words:
        raise NameParseError(f"no target name in {stem!r}: {CANONICAL_HINT}")
    # Drop scene-label words ("scene", "ctx") that directly precede a number.
    for i in list(words):
        nxt = items[i + 1] if i + 1 < len(items) else None
        if items[i][1].lower() in _SCENE_WORDS and nxt is not None and nxt[0] == "c" and not nxt[1]:
            words.remove(i)
    if not words or words != list(range(words[0], words[-1] + 1)):
        raise NameParseError(f"expected one target name in {stem!r}, found words apart: {CANONICAL_HINT}")
    target_word = "".join(items[i][1] for i in words)
    before = [it for it in items[: words[0]] if it[0] == "c"]
    after = [it for it in items[words[-1] + 1 :] if it[0] == "c"]
    numbers = before + after
    if any(it[1] for it in numbers):
        coords = {a: v for kind, a, v in numbers if a}
        if len(coords) != 3 or len([it for it in numbers if it[1]]) != 3:
            raise NameParseError(f"expected axis letters x, y, z once each in {stem!r}: {CANONICAL_HINT}")
        others = [it for it in numbers if not it[1]]
        xyz = (coords["x"], coords["y"], coords["z"])
    elif len(before) == 3 and len(after) <= 1:
        xyz, others = tuple(v for _, _, v in before), after
    elif len(after) == 3 and len(before) <= 1:
        xyz, others = tuple(v for _, _, v in after), before
    else:
        raise NameParseError(
            f"expected three coordinates then the target then the scene id in {stem!r} "
            f"(found {len(before)} number(s) before and {len(after)} after the target): {CANONICAL_HINT}"
        )
    if len(others) > 1 or (others and scene is not None):
        raise NameParseError(f"more than one scene id in {stem!r}: {CANONICAL_HINT}")
    if others:
        number = others[0][2]
        if number < 0:
            raise NameParseError(f"negative scene id in {stem!r}: {CANONICAL_HINT}")
        scene = str(number)
    target = normalize_target(target_word)
    return ParsedName(xyz=(int(xyz[0]), int(xyz[1]), int(xyz[2])), target=target, scene=scene)


def is_image_name(name: str) -> bool:
    """Whether a file name has an accepted image extension (any case)."""
    return name.lower().endswith(IMAGE_EXTS)
