"""Attribution controls shared by the worlds' CLIs: what a row would be without the learned part.

:func:`random_weights` gives a denoiser of the same architecture and schedule whose parameters
are a fresh draw (every parameter then moved by ``scale`` x N(0, 1), since a fresh draw's last
layer is zero and would return one constant plan): the planner, its triggers and psi run
unchanged, so the row shows what the hand-written parts (the map, the walk to the plan's goal)
achieve with a denoiser that learned nothing.
"""
from __future__ import annotations

import jax

RANDOM_WEIGHTS_SEED = 0
"""The seed of the random weights (a control, not a choice: any seed serves)."""


def random_weights(denoiser, seed: int = RANDOM_WEIGHTS_SEED, scale: float = 0.1):
    """A ``LoadedDenoiser`` like ``denoiser`` (a trained ``Denoiser``'s) with random parameters
    of the same shapes: the model's own initialiser, then every leaf + scale * N(0, 1).
    Constants written before training (``frozen_*`` parameters, e.g. a features denoiser's cell
    names) are kept. ValueError for a denoiser that is not a ``diffplan.denoiser.Denoiser``."""
    from diffplan.denoiser import Denoiser, ModuleApply, init_params
    from diffplan.train_state import FROZEN_PREFIX

    model = getattr(denoiser.apply_fn, "model", None)
    if not isinstance(denoiser.apply_fn, ModuleApply) or not isinstance(model, Denoiser):
        raise ValueError("random weights need a Denoiser checkpoint (this one is "
                         f"{type(model or denoiser.apply_fn).__name__})")
    key = jax.random.PRNGKey(seed)
    fresh = init_params(model, key)["params"]
    leaves, tree = jax.tree.flatten(fresh)
    keys = jax.random.split(jax.random.fold_in(key, 1), len(leaves))
    params = jax.tree.unflatten(tree, [x + scale * jax.random.normal(k, x.shape, x.dtype)
                                       for x, k in zip(leaves, keys)])
    params = {name: (denoiser.params[name] if name.startswith(FROZEN_PREFIX) else value)
              for name, value in params.items()}
    return denoiser.replace(params=params)
