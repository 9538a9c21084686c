"""A tiny name -> dataset-generator registry (used by ``recipes/make_dataset.py``).

A generator is a callable ``fn(env, **options) -> (td, meta)`` returning a trajectory batch
(see ``docs/conventions.md``) and its metadata. A generator module registers itself at import
time with :func:`register_dataset_generator`; :func:`get_dataset_generator` imports the known
generator modules of this package lazily, so adding ``torchrl_ftb/datasets/locomotion.py``
(which registers itself) needs no change to the CLI.

Example:
    >>> from torchrl_ftb.datasets.registry import get_dataset_generator
    >>> get_dataset_generator("button-press-v3").name
    'metaworld'
"""
from __future__ import annotations

import importlib
import importlib.util
from dataclasses import dataclass
from typing import Callable

__all__ = ["DatasetGenerator", "register_dataset_generator", "get_dataset_generator", "dataset_generators"]

# modules of this package that register generators when imported
_GENERATOR_MODULES = ("torchrl_ftb.datasets.metaworld", "torchrl_ftb.datasets.locomotion")


@dataclass(frozen=True)
class DatasetGenerator:
    """A registered generator: ``fn(env, **options) -> (td, meta)`` for envs ``matches(env)`` accepts."""

    name: str
    fn: Callable
    matches: Callable[[str], bool]
    description: str = ""


_REGISTRY: dict[str, DatasetGenerator] = {}


def register_dataset_generator(
    name: str, fn: Callable, *, matches: Callable[[str], bool], description: str = ""
) -> DatasetGenerator:
    """Register ``fn`` under ``name`` for the env names ``matches`` accepts (re-registering replaces)."""
    gen = DatasetGenerator(name=name, fn=fn, matches=matches, description=description)
    _REGISTRY[name] = gen
    return gen


def _import_generator_modules() -> None:
    for module in _GENERATOR_MODULES:
        if importlib.util.find_spec(module) is not None:
            importlib.import_module(module)


def dataset_generators() -> dict[str, DatasetGenerator]:
    """All registered generators (after importing this package's generator modules)."""
    _import_generator_modules()
    return dict(_REGISTRY)


def get_dataset_generator(env: str) -> DatasetGenerator:
    """The generator that handles ``env``.

    Raises:
        ValueError: no generator accepts ``env`` (the message lists the registered ones).
    """
    gens = dataset_generators()
    for gen in gens.values():
        if gen.matches(env):
            return gen
    described = "; ".join(f"{g.name}: {g.description}" for g in gens.values()) or "none registered"
    raise ValueError(f"no dataset generator for env {env!r} (generators: {described})")
