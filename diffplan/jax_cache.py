"""JAX's persistent compilation cache, shared by every CLI, benchmark and the tests.

Compiled programs are reused across processes, so a second run of an experiment skips most of
its compile time. The directory is the argument, else $DIFFPLAN_JAX_CACHE, else
~/.cache/diffplan-jax.
"""
from __future__ import annotations

import os

import jax

DEFAULT_CACHE_DIR = "~/.cache/diffplan-jax"


def enable_compilation_cache(cache_dir: str | None = None) -> str | None:
    """Turns the cache on; returns its directory, or None if it cannot be created (the run then
    goes on without a persistent cache)."""
    path = os.path.expanduser(cache_dir or os.environ.get("DIFFPLAN_JAX_CACHE",
                                                          DEFAULT_CACHE_DIR))
    try:
        os.makedirs(path, exist_ok=True)
    except OSError:
        return None
    jax.config.update("jax_compilation_cache_dir", path)
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.5)
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
    return path
