"""One entry point from an env name to its offline dataset: :func:`make_dataset`.

Dispatch by :func:`torchrl_ftb.envs.env_kind`: ``"toy"`` → :func:`torchrl_ftb.testing.make_toy_dataset`,
a Meta-World v3 task → :func:`torchrl_ftb.datasets.make_metaworld_dataset` (IPL recipe, cached),
a locomotion env → the registered locomotion generator
(:func:`torchrl_ftb.datasets.get_dataset_generator`, D4RL-style ``<env>-<kind>`` datasets made
from our shipped behaviour policies, cached). The env for the same name comes from
:func:`torchrl_ftb.envs.make_env`; the two agree on observation/action dims.

Example:
    >>> from torchrl_ftb.datasets import make_dataset
    >>> td, meta = make_dataset("toy", num_trajectories=8, horizon=16, seed=0)
    >>> td.batch_size, meta["env_id"]
    (torch.Size([8, 16]), 'toy')
    >>> td, meta = make_dataset("hopper", kind="medium-replay", seed=0)  # doctest: +SKIP
"""
from __future__ import annotations

import inspect
import os
from typing import Any, Callable, Mapping

from tensordict import TensorDict

from torchrl_ftb.envs import LOCOMOTION_ENVS, env_kind, locomotion_env_id

__all__ = ["dataset_kwargs", "make_dataset"]

# set by make_dataset itself, never through **options
_RESERVED = ("seed", "cache_dir", "out", "progress")


def _check_options(fn: Callable, options: dict[str, Any], *, name: str, what: str) -> None:
    """Unknown keyword options are a ``ValueError`` naming the accepted ones."""
    params = inspect.signature(fn).parameters
    accepted = [k for k, p in params.items() if p.kind is inspect.Parameter.KEYWORD_ONLY and k not in _RESERVED]
    unknown = sorted(set(options) - set(accepted))
    if unknown:
        raise ValueError(f"make_dataset({name!r}): unknown option(s) {unknown} for {what}; accepted: {accepted}")


def _locomotion_dataset_name(name: str, kind: str | None) -> str:
    from torchrl_ftb.datasets.locomotion import LOCOMOTION_KINDS

    short = next(k for k, v in LOCOMOTION_ENVS.items() if v == locomotion_env_id(name))
    if kind not in LOCOMOTION_KINDS:
        raise ValueError(
            f"make_dataset({name!r}): a locomotion dataset needs kind= one of {list(LOCOMOTION_KINDS)} "
            f"(D4RL's '<env>-<kind>'), got {kind!r}"
        )
    return f"{short}-{kind}"


def make_dataset(
    name: str,
    *,
    kind: str | None = None,
    seed: int = 0,
    cache_dir: str | os.PathLike | None = None,
    progress: bool = True,
    **options: Any,
) -> tuple[TensorDict, dict]:
    """The offline trajectory batch ``[N, H]`` of env ``name`` and its metadata.

    Args:
        name: ``"toy"``, a Meta-World v3 task, a locomotion env (``"hopper"``, ``"Hopper-v5"``,
            ...) or a locomotion dataset name (``"hopper-medium-replay"``, ``-v2`` accepted).
        kind: locomotion only: ``"medium"``, ``"medium-replay"`` or ``"medium-expert"``
            (not needed when ``name`` already names the dataset).
        seed: dataset seed.
        cache_dir: cache root (Meta-World and locomotion; default ``$TORCHRL_FTB_DATA`` or
            ``~/.cache/torchrl_ftb/datasets``); ignored for toy (generated in memory).
        progress: tqdm bars while generating (Meta-World and locomotion).
        **options: the generator's own options. Toy: ``num_trajectories``, ``horizon``,
            ``noise`` (:func:`~torchrl_ftb.testing.make_toy_dataset`); Meta-World:
            ``episodes_per_group``, ``noise``, ``max_steps``, ``num_workers``, ``groups``
            (:func:`~torchrl_ftb.datasets.make_metaworld_dataset`); locomotion:
            ``num_transitions``, ``deterministic`` (see ``torchrl_ftb.datasets.locomotion``).
            ``None`` values mean "the generator's default".

    Returns:
        ``(td, meta)``: the trajectory batch (``docs/conventions.md``) and its metadata
        (``meta["env_id"]``; ``meta["path"]`` of the cached copy, ``None`` for toy).

    Raises:
        ValueError: unknown name, missing/invalid ``kind``, unknown option.

    Example:
        >>> td, meta = make_dataset("button-press-v3", episodes_per_group=1, max_steps=20,
        ...                         progress=False)  # doctest: +SKIP
        >>> td.batch_size  # doctest: +SKIP
        torch.Size([4, 20])
    """
    options = {k: v for k, v in options.items() if v is not None}
    try:
        family = env_kind(name)
    except ValueError:
        family = None  # maybe a locomotion dataset name such as "hopper-medium-replay"
    if family is not None and family != "locomotion" and kind is not None:
        raise ValueError(f"make_dataset({name!r}): kind={kind!r} is for locomotion datasets only")
    if family == "toy":
        from torchrl_ftb.testing import make_toy_dataset

        _check_options(make_toy_dataset, options, name=name, what="make_toy_dataset")
        td = make_toy_dataset(seed=int(seed), **options)
        meta = {"env_id": "toy", "domain": "toy", "seed": int(seed), "num_trajectories": int(td.batch_size[0]),
                "horizon": int(td.batch_size[1]), "path": None}
        return td, meta
    if family == "metaworld":
        from torchrl_ftb.datasets.metaworld import make_metaworld_dataset

        _check_options(make_metaworld_dataset, options, name=name, what="make_metaworld_dataset")
        return make_metaworld_dataset(name, seed=int(seed), cache_dir=cache_dir, progress=progress, **options)

    from torchrl_ftb.datasets.registry import get_dataset_generator

    if family == "locomotion":
        dataset = _locomotion_dataset_name(name, kind)
        generator = get_dataset_generator(dataset)
    else:  # a dataset name? else the unknown-env error, which lists the valid names
        dataset = name
        try:
            generator = get_dataset_generator(dataset)
        except ValueError:
            generator = None
        if generator is None or generator.name != "locomotion":
            env_kind(name)
        if kind is not None:
            raise ValueError(f"make_dataset({name!r}): the name already selects the dataset; drop kind={kind!r}")
    _check_options(generator.fn, options, name=name, what=f"the {generator.name!r} generator")
    return generator.fn(dataset, seed=int(seed), out=None if cache_dir is None else str(cache_dir),
                        progress=progress, **options)


#: keys of a recipe's ``dataset:`` section that each env family's generator takes
_SECTION_KEYS = {"toy": ("num_trajectories", "horizon"),
                 "metaworld": ("episodes_per_group", "noise", "num_workers", "groups")}


def dataset_kwargs(
    name: str, section: Mapping[str, Any], *, max_episode_steps: int | None = None, progress: bool = True
) -> dict[str, Any]:
    """:func:`make_dataset` keywords for env ``name`` from a flat, all-families config section.

    The recipes (``recipes/config/*.yaml``) share one ``dataset:`` section for every env
    family; this picks what ``name``'s family uses, so the same config serves toy, Meta-World
    and locomotion runs: ``seed`` and ``cache_dir`` always; toy ``num_trajectories``,
    ``horizon``; Meta-World ``episodes_per_group``, ``noise``, ``num_workers``, ``groups`` and
    ``max_steps=max_episode_steps``; locomotion the ``options`` mapping (``kind``,
    ``num_transitions``, ``deterministic``). Missing keys take the generator's default.

    Args:
        name: env name (see :func:`torchrl_ftb.envs.env_kind`).
        section: mapping (``dict`` or OmegaConf ``DictConfig``) with the keys above.
        max_episode_steps: Meta-World time limit (= padded horizon).
        progress: tqdm bars while generating.

    Example:
        >>> section = {"seed": 0, "num_trajectories": 8, "horizon": 16, "noise": 1.0, "options": {}}
        >>> dataset_kwargs("toy", section, progress=False)
        {'seed': 0, 'cache_dir': None, 'progress': False, 'num_trajectories': 8, 'horizon': 16}
        >>> td, meta = make_dataset("toy", **dataset_kwargs("toy", section, progress=False))
    """
    family = env_kind(name)
    out: dict[str, Any] = {"seed": int(section.get("seed", 0)), "cache_dir": section.get("cache_dir"),
                           "progress": bool(progress)}
    if family == "locomotion":
        return {**out, **dict(section.get("options") or {})}
    out.update({k: section[k] for k in _SECTION_KEYS[family] if section.get(k) is not None})
    if family == "metaworld" and max_episode_steps is not None:
        out["max_steps"] = int(max_episode_steps)
    return out
