"""Pytree helpers without flax (the engine imports only jax and numpy), for the engine and every room above it: a
dataclass that is also a JAX pytree, and a pytree as flat named host arrays (how trees travel on the bus, see
`actors.wire` and `curriculum.wire`, and are shown to people)."""

from __future__ import annotations

import dataclasses
from typing import Any, TypeVar

import jax
import jax.numpy as jnp
import numpy as np

T = TypeVar("T")


def pytree_dataclass(cls: type[T]) -> type[T]:
    """Freeze `cls` as a dataclass whose fields are all pytree leaves, with a `replace` method."""
    cls = dataclasses.dataclass(frozen=True)(cls)
    cls.replace = dataclasses.replace  # type: ignore[attr-defined]
    return jax.tree_util.register_dataclass(cls)


def path_name(path: tuple[Any, ...]) -> str:
    """`a/b/0/c` for a pytree key path (dict keys, NamedTuple and dataclass fields, sequence indices)."""
    parts = []
    for entry in path:
        for attribute in ("name", "key", "idx"):
            if hasattr(entry, attribute):
                parts.append(str(getattr(entry, attribute)))
                break
        else:
            parts.append(str(entry))
    return "/".join(parts)


def tree_arrays(tree: Any) -> dict[str, np.ndarray]:
    """A pytree as {path name: host numpy array} (one device-to-host copy per leaf)."""
    leaves = jax.tree_util.tree_flatten_with_path(tree)[0]
    host = jax.device_get([leaf for _, leaf in leaves])
    return {path_name(path): np.asarray(value) for (path, _), value in zip(leaves, host, strict=True)}


def tree_from_arrays(arrays: dict[str, np.ndarray], template: Any) -> Any:
    """The pytree of `template`'s structure with the arrays of the same names (checked by a schema first)."""
    paths, treedef = jax.tree_util.tree_flatten_with_path(template)
    return jax.tree.unflatten(treedef, [arrays[path_name(path)] for path, _ in paths])


def all_finite(tree: Any) -> jax.Array:
    """A boolean scalar: whether every floating-point leaf of `tree` holds finite numbers only (no NaN, no
    infinity); integer leaves are not looked at. Traceable, so the PPO update can refuse its own result."""
    checks = [jnp.isfinite(leaf).all() for leaf in jax.tree.leaves(tree) if jnp.issubdtype(leaf.dtype, jnp.inexact)]
    return jnp.stack(checks).all() if checks else jnp.asarray(True)


def count_non_finite(tree: Any) -> tuple[int, int]:
    """(non-finite floats, floats) over the floating-point leaves of `tree`, on the host: what an error message
    says about parameters that must not be checkpointed, exported or published."""
    bad = total = 0
    for leaf in jax.device_get(jax.tree.leaves(tree)):
        array = np.asarray(leaf)
        if array.dtype.kind == "f":
            total += array.size
            bad += int(array.size - np.count_nonzero(np.isfinite(array)))
    return bad, total
