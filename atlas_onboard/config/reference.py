"""The reference of every setting, from the declarations (:mod:`.settings`, :mod:`.model`): one row per
YAML key with its default, unit, range and meaning. ``python -m atlas_onboard.config.reference``
prints ``docs/settings.md`` (a test checks that the file is current).
"""

from __future__ import annotations

import dataclasses
import sys
from dataclasses import dataclass
from enum import Enum
from typing import Any

from atlas_onboard.config import model, settings
from atlas_onboard.config.fields import REQUIRED, declared, kind_of, range_text

# Where each class's settings sit in the file: (YAML path of the section, class, only these keys).
# `<name>` is any entity, `<entity>` an entity with a node or `defaults`, `[]` any item of a list.
SECTIONS: tuple[tuple[str, type, tuple[str, ...]], ...] = (
    ("", model.FileOptions, ()),
    ("conventions", model.Conventions, ()),
    ("fusion", settings.FusionConfig, ()),
    ("entities.<name>.sensors[]", model.SensorConfig, ()),
    ("entities.<name>.sensors[]", model.SensorPose, ()),
    ("entities.<name>.sensors[].camera", settings.CameraConfig, ()),
    ("entities.<name>.markers[]", model.MarkerConfig, ()),
    ("nodes.<entity>", settings.NodeConfig, ()),
    ("nodes.<entity>.autopilot", settings.LinkConfig, ("url", "signing")),
    ("nodes.<entity>.autopilot", settings.AutopilotConfig, ()),
    ("nodes.<entity>.autopilot.signing", settings.SigningConfig, ()),
    ("nodes.<entity>.autopilot.origin", settings.GlobalOrigin, ()),
    ("nodes.<entity>.peers[]", settings.LinkConfig, ()),
    ("nodes.<entity>.peers[].signing", settings.SigningConfig, ()),
    ("nodes.<entity>.record", settings.RecordConfig, ()),
    ("nodes.<entity>.refine", settings.RefineConfig, ()),
    ("nodes.<entity>.landing", settings.LandingConfig, ()),
)


@dataclass(frozen=True)
class Row:
    """One setting of the file."""

    path: str  # e.g. "fusion.edge_timeout_s", "nodes.<entity>.peers[].url"
    default: str  # as the docs and the example write it: "0.25", "none", "required", ...
    unit: str
    allowed: str  # the range, or the choices
    doc: str


def format_default(f: dataclasses.Field[Any]) -> str:
    """A setting's default as the docs and ``example.yaml`` write it."""
    value = f.default
    if value is REQUIRED:
        return f.metadata["fallback"] or "required"
    if value is None:
        return "none"
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, Enum):
        return str(value.value)
    if isinstance(value, float):
        return f"{value:g}"
    if value == "":
        return '""'
    if value == ():
        return "[]"
    return str(value)


def _allowed(cls: type, name: str) -> str:
    meta = declared(cls)[name].metadata
    kind = kind_of(cls, name)
    choices: tuple[str, ...] = meta["choices"]
    if isinstance(kind, type) and issubclass(kind, Enum):
        choices = tuple(str(e.value) for e in kind)
    if choices:
        shown = [c or '""' for c in choices]
        return f"one of {len(shown)} names (docs/markers.md)" if len(shown) > 8 else ", ".join(shown)
    text = range_text(meta)
    if text and meta["off"] is not None:
        text = f"{meta['off']:g} (off) or {text}"
    if not text and kind is bool:
        text = "true, false"
    return text


def rows() -> list[Row]:
    """Every setting of the file, section by section in :data:`SECTIONS` order."""
    out = []
    for section, cls, only in SECTIONS:
        for name, f in declared(cls).items():
            if only and name not in only:
                continue
            key = f.metadata["key"] or name
            path = f"{section}.{key}" if section else key
            out.append(Row(path, format_default(f), f.metadata["unit"], _allowed(cls, name), f.metadata["doc"]))
    return out


def markdown() -> str:
    """``docs/settings.md``."""
    lines = [
        "# Settings",
        "",
        "Every key of the world file, generated from the declarations in `atlas_onboard/config/settings.py`",
        "and `model.py` by `python -m atlas_onboard.config.reference > docs/settings.md` (a test checks that",
        "this page is current). `<name>` is any entity, `<entity>` an entity with a node or `defaults`, `[]`",
        "any item of a list. `config/example.yaml` shows each key in place.",
        "",
        "| key | default | unit | allowed | meaning |",
        "|---|---|---|---|---|",
    ]
    for r in rows():
        cells = [f"`{r.path}`", f"`{r.default}`", r.unit, r.allowed, r.doc]
        lines.append("| " + " | ".join(c.replace("|", "\\|") for c in cells) + " |")
    return "\n".join(lines) + "\n"


def main() -> int:
    sys.stdout.write(markdown())
    return 0


if __name__ == "__main__":
    sys.exit(main())
