"""The object sets of the generalisation protocol (`benchmarks.generalise`): procedural `dev` / `dev-b` and the real
`real-dev` / `real-eval`, each object with its seed, training light and two held-out lights, drawn from its seed."""

from __future__ import annotations

import argparse
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from benchmarks.real_objects import REPO_ROOT, set_files
from matspray.errors import ConfigError
from matspray.render.shade.lights import BUILTINS

# The sets were drawn while the packaged HDRIs studio-small and venice-sunset were named studio and sunset, names
# under which `load_envmap` gave the built-in lights: the sets keep drawing those names, so each object keeps the
# lights it was measured under.
DRAWN_AS = {"studio-small": "studio", "venice-sunset": "sunset"}
SET_SEEDS = {"dev": 1000, "dev-b": 2000, "real-dev": 3000, "real-eval": 4000}  # object i: seed SET_SEEDS[set] + i
# dev-b was the procedural evaluation set, until its many passes at successive defaults made it a development set
RENAMED_SETS = {"eval": "dev-b"}
REAL_SETS = ("real-dev", "real-eval")  # glTF objects (benchmarks/real_objects.py); the others are procedural
EVAL_SETS = ("real-eval",)  # run once, with settings chosen on the development sets
MAX_OBJECTS = 1000  # keeps the sets' seeds disjoint
DEFAULT_OBJECTS = 6  # of a procedural set; a real set's default is all of its objects


@dataclass(frozen=True)
class ObjectSpec:
    name: str
    seed: int
    env: str  # training light
    relight_envs: tuple[str, ...]  # the two held-out lights
    asset: str | None = None  # a real set's glTF file, relative to the repository (None: a procedural object)


def renamed(which: str) -> str:
    return (
        f"the object set '{which}' is now named '{RENAMED_SETS[which]}' (it was used to choose settings); "
        "the evaluation set is real-eval"
    )


def set_name(text: str) -> str:
    """`--set`'s type: a renamed set's old name is refused with its new name (argparse shows the message)."""
    if text in RENAMED_SETS:
        raise argparse.ArgumentTypeError(renamed(text))
    return text


def object_set(which: str, count: int | None, hdris: list[str]) -> list[ObjectSpec]:
    """The first `count` objects of set `which` (None: DEFAULT_OBJECTS, or all of a real set's): a training HDRI (a
    built-in light when there are no HDRIs) and two other relighting lights from HDRIs and built-ins, drawn from the
    object's seed."""
    if which in RENAMED_SETS:
        raise ConfigError(renamed(which))
    if which not in SET_SEEDS:
        raise ConfigError(f"unknown object set '{which}'; choose one of {', '.join(SET_SEEDS)}")
    assets = [str(path.relative_to(REPO_ROOT)) for path in set_files(which)] if which in REAL_SETS else None
    size = MAX_OBJECTS if assets is None else len(assets)
    count = (DEFAULT_OBJECTS if assets is None else size) if count is None else count
    if not 1 <= count <= size:
        raise ConfigError(f"--objects must be in [1, {size}] for the set {which}, got {count}")
    train_pool = sorted(DRAWN_AS.get(name, name) for name in hdris) or list(BUILTINS)
    pool = sorted(set(train_pool) | set(BUILTINS))
    objects = []
    for index in range(count):
        seed = SET_SEEDS[which] + index
        rng = np.random.default_rng([seed, 21])
        env = train_pool[int(rng.integers(len(train_pool)))]
        others = [name for name in pool if name != env]
        relight = tuple(others[int(i)] for i in rng.choice(len(others), size=2, replace=False))
        if assets is None:
            objects.append(ObjectSpec(f"{which}-{index:02d}-seed{seed}", seed, env, relight))
        else:
            name = f"{which}-{index:02d}-{Path(assets[index]).stem}"
            objects.append(ObjectSpec(name, seed, env, relight, assets[index]))
    return objects


def with_training_light(objects: list[ObjectSpec], light: str | None) -> list[ObjectSpec]:
    """The objects trained under `light` instead of their own (None: as drawn), named for it so that their folders
    are their own; an object relit under that light is refused (its held-out light would be its training one)."""
    if light is None:
        return objects
    clash = [spec.name for spec in objects if light in spec.relight_envs]
    if clash:
        raise ConfigError(f"--train-light {light}: {', '.join(clash)} are relit under it; choose another light")
    return [replace(spec, name=f"{spec.name}-train-{light}", env=light) for spec in objects]


def objects_part(which: str, start: int, count: int | None, hdris: list[str]) -> list[ObjectSpec]:
    """Objects start .. start + count - 1 of set `which` (count None: to the default's end): one part of a pass
    split over jobs (`--start`)."""
    return object_set(which, None if count is None else start + count, hdris)[start:]
