"""The presets, read from presets.json: the one list of them. The add-on reads the same file
for its menu (names, labels, descriptions) without importing torch; a new preset is one entry
there."""

from __future__ import annotations

import json
from pathlib import Path

from ..core.errors import NerfError
from .train_config import TrainConfig

PRESETS_FILE = Path(__file__).with_name("presets.json")


def _merged(base: dict, changes: dict, where: str) -> dict:
    """``base`` with ``changes`` applied, nested groups merged; an unknown key is an error."""
    merged = dict(base)
    for key, value in changes.items():
        if key not in base:
            raise NerfError(f"{PRESETS_FILE}: {where}: no setting {key!r}")
        merged[key] = _merged(base[key], value, f"{where}.{key}") if isinstance(value, dict) else value
    return merged


def load_presets(path: Path = PRESETS_FILE) -> dict[str, TrainConfig]:
    """Every preset of ``path``, in its order (the add-on's menu order); an entry that
    ``extends`` another starts from that one's settings, else from TrainConfig's defaults."""
    entries = json.loads(path.read_text(encoding="utf-8"))
    built: dict[str, TrainConfig] = {}

    def build(name: str) -> TrainConfig:
        if name not in built:
            entry = entries[name]
            base = build(entry["extends"]) if "extends" in entry else TrainConfig(preset=name)
            data = _merged(base.to_dict(), entry["settings"], name)
            built[name] = TrainConfig.from_dict({**data, "preset": name})
        return built[name]

    return {name: build(name) for name in entries}


PRESETS: dict[str, TrainConfig] = load_presets()
# What a new run trains without a preset named: the one the README, the add-on and the demo use.
DEFAULT_PRESET = "auto"


def preset_config(name: str) -> TrainConfig:
    try:
        return PRESETS[name]
    except KeyError:
        raise NerfError(f"unknown preset {name!r}; choose one of {', '.join(sorted(PRESETS))}") from None
