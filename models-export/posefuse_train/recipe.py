"""Training recipes: TOML files naming every number of a run (posefuse_train/recipes/*.toml), read
into the trainer's configs. `--set section.key=value` overrides one value (a quick run, a sweep)
and is recorded with the recipe."""

from __future__ import annotations

import copy
import dataclasses
import json
import sys
from pathlib import Path

from .config import CameraNetConfig, PointNetConfig
from .keypoints import K
from .train import TrainCameraConfig, TrainPointConfig

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover - Python 3.10
    import tomli as tomllib

RECIPES = Path(__file__).resolve().parent / "recipes"
SECTIONS = ("recipe", "data", "pipeline", "run", "camera", "point")


def builtin() -> list[str]:
    return sorted(p.stem for p in RECIPES.glob("*.toml"))


def load(name_or_path: str, overrides: list[str] | None = None) -> dict:
    """A recipe by name (cpu, paper) or path, with `section.key=value` overrides applied (the
    value read as TOML: numbers, strings in quotes or bare, lists, true/false)."""
    path = Path(name_or_path)
    if not path.suffix:
        path = RECIPES / f"{name_or_path}.toml"
    if not path.exists():
        raise ValueError(f"no recipe {name_or_path!r}: a file, or one of {', '.join(builtin())}")
    recipe = tomllib.loads(path.read_text())
    for over in overrides or []:
        set_value(recipe, over)
    validate(recipe)
    return recipe


def set_value(recipe: dict, assignment: str) -> None:
    key, sep, raw = assignment.partition("=")
    if not sep or "." not in key:
        raise ValueError(f"--set {assignment!r}: expected section.key=value")
    try:
        value = tomllib.loads(f"v = {raw}")["v"]
    except tomllib.TOMLDecodeError:
        value = raw  # a bare string
    *parents, leaf = key.split(".")
    node = recipe
    for p in parents:
        node = node.setdefault(p, {})
    if leaf not in node and leaf not in _defaulted(parents):
        raise ValueError(f"--set {key}: the recipe has no such key")
    node[leaf] = value


def _defaulted(section: list[str]) -> set[str]:
    """Keys a recipe may leave out, its config's default standing in (a value added to the trainer
    after a recipe was written, which that recipe's bundle was trained without)."""
    return {
        ("camera",): _fields(TrainCameraConfig) | _fields(CameraNetConfig),
        ("point",): _fields(TrainPointConfig) - {"fusion"},
        ("point", "net"): _fields(PointNetConfig) - {"in_features"},
    }.get(tuple(section), set())


def validate(recipe: dict) -> None:
    unknown = set(recipe) - set(SECTIONS)
    if unknown:
        raise ValueError(f"unknown recipe sections {sorted(unknown)}")
    camera_config(recipe)
    point_config(recipe, fusion=True)


def _fields(cls) -> set[str]:
    return {f.name for f in dataclasses.fields(cls)}


def _tuples(d: dict) -> dict:
    return {k: tuple(v) if isinstance(v, list) else v for k, v in d.items()}


def camera_config(recipe: dict) -> tuple[CameraNetConfig, TrainCameraConfig]:
    c = dict(recipe["camera"])
    net = {k: c.pop(k) for k in list(c) if k in _fields(CameraNetConfig)}
    unknown = set(c) - _fields(TrainCameraConfig)
    if unknown:
        raise ValueError(f"[camera]: unknown keys {sorted(unknown)}")
    train = TrainCameraConfig(**_tuples(c))
    # a facing target needs the head it trains (docs/TRAINING.md, "Facing target")
    net.setdefault("facing_head", train.facing_weight > 0)
    return CameraNetConfig(**net), train


def point_config(recipe: dict, fusion: bool) -> tuple[PointNetConfig, TrainPointConfig]:
    c = copy.deepcopy(recipe["point"])
    net = c.pop("net", {})
    unknown = set(c) - _fields(TrainPointConfig)
    if unknown:
        raise ValueError(f"[point]: unknown keys {sorted(unknown)}")
    net_cfg = PointNetConfig(in_features=3 + K if fusion else 3, **_tuples(net))
    return net_cfg, TrainPointConfig(fusion=fusion, **_tuples(c))


def dumps(recipe: dict) -> str:
    """A canonical text of the recipe, to tell whether a resumed run is the same run."""
    return json.dumps(recipe, sort_keys=True)
