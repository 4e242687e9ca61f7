"""What both worlds' denoisers share: the model sizes, the training configuration built from an
experiment's recipe numbers, and one call that trains a denoiser with a world's training recipe
(``envs.<world>.training.Recipe``)."""
from __future__ import annotations

import time

MODEL_SIZES = {
    # For tests and smoke runs: compiles and trains in seconds, learns little.
    "tiny": dict(embed_dim=8, widths=(8, 16), num_res_blocks=1, attn_levels=(), cross_attn_levels=(1,),
                 text_dim=16, text_layers=1, text_heads=2, groups=4, head_dim=8),
    # The shipped denoisers (grid world and Kuka), sized for a 2-core CPU.
    # Widths (16, 32, 64): ~50 MFLOP per sample. experiments/bench_unet.py measured a
    # 2.8M-parameter (32, 64, 128) UNet at ~1.6x the forward time and ~1.8x the train-step time
    # of this size on this CPU; on-the-fly evaluation is dominated by denoiser calls.
    "default": dict(embed_dim=32, widths=(16, 32, 64), num_res_blocks=1, attn_levels=(2,),
                    cross_attn_levels=(0, 1, 2), text_dim=64, text_layers=2, text_heads=4,
                    groups=8, head_dim=16),
}


def denoiser_config(size: str, *, vocab_size: int, max_tokens: int, num_cond_channels: int,
                    num_gen_channels: int, grid_repr: str = "embed", context_dim: int = 0,
                    cell_context: bool | None = None, standardize: bool | None = None,
                    cell_lookup: bool | None = None):
    """The DenoiserConfig of a model size on a world's planning tensor and vocabulary (or,
    with context_dim D > 0, a frozen pretrained text encoder's D-wide token features:
    vocab_size then counts the world's cell tokens only). With features, by default, the
    cells are embedded by their names' features (cell_context, with grid_repr "embed") and
    the features standardised with the training sentences' statistics (standardize), and each
    cell's name looked up in the instruction (cell_lookup, with cell_context)."""
    from diffplan.denoiser import DenoiserConfig

    if size not in MODEL_SIZES:
        raise ValueError(f"unknown model size {size!r}; expected one of {sorted(MODEL_SIZES)}")
    if cell_context is None:
        cell_context = bool(context_dim) and grid_repr == "embed"
    return DenoiserConfig(vocab_size=vocab_size, max_tokens=max_tokens,
                          num_cond_channels=num_cond_channels,
                          num_gen_channels=num_gen_channels, grid_repr=grid_repr,
                          context_dim=context_dim, cell_context=cell_context,
                          cell_lookup=cell_context if cell_lookup is None else cell_lookup,
                          standardize=bool(context_dim) if standardize is None else standardize,
                          **MODEL_SIZES[size])


def warmup(warmup_steps: int, steps: int) -> int:
    """The warm-up of a run of ``steps`` steps: at most a tenth of them."""
    return min(warmup_steps, max(steps // 10, 0))


def train_config(*, seed: int, steps: int, batch_size: int, lr: float, warmup_steps: int,
                 num_gen_channels: int, prediction: str, checkpoint_every: int,
                 max_log_every: int, num_train_timesteps: int = 100,
                 timestep_power: float = 1.0, objective: str = "diffusion"):
    """The TrainConfig of an experiment: warm-up at most a tenth of the steps, a log every
    min(max_log_every, steps / 10) steps, num_train_timesteps diffusion training timesteps
    (the paper's 100 unless the world's spec says otherwise), drawn with timestep_power (the
    paper's uniform draw: 1). objective "goal" trains the learned-goal baseline instead
    (``diffplan.baselines.goal``), which predicts the clean plan ("x0") by construction."""
    from diffplan.train import TrainConfig

    return TrainConfig(seed=seed, steps=steps, batch_size=batch_size, lr=lr,
                       warmup_steps=warmup(warmup_steps, steps),
                       num_gen_channels=num_gen_channels,
                       prediction="x0" if objective == "goal" else prediction,
                       num_train_timesteps=num_train_timesteps, timestep_power=timestep_power,
                       objective=objective,
                       checkpoint_every=checkpoint_every,
                       log_every=max(1, min(max_log_every, steps // 10)))


def train_denoiser(model_config, config, recipe, out_dir: str, *, model_size: str,
                   progress: bool = True, callback=None):
    """Trains a Denoiser of model_config with ``config`` (a TrainConfig) on the recipe's batches
    into out_dir (resuming if it holds a checkpoint of the same settings); the checkpoint's
    metadata records the recipe and the model size. With ``config.objective`` "goal" the same
    network learns the learned-goal baseline instead (``diffplan.baselines.goal``). Returns
    (TrainResult, seconds). A recipe whose ``sentences()`` gives a sentence table (text
    "pretrained") trains on the pretrained text features assembled from it inside the step
    (``diffplan.train.train(..., sentences=...)``); a recipe's ``fixed_params()`` (if it has
    one) gives the model's constants, e.g. its cells' name features."""
    from diffplan.baselines.goal import GoalClassifier
    from diffplan.denoiser import Denoiser
    from diffplan.train import train

    start = time.time()
    model = (GoalClassifier if config.objective == "goal" else Denoiser)(model_config)
    sentences = getattr(recipe, "sentences", lambda: None)()
    fixed = getattr(recipe, "fixed_params", lambda model_config: None)(model_config)
    result = train(model, model_config, config, recipe.batch_fn(), out_dir,
                   init_batch=recipe.init_batch(), progress=progress, callback=callback,
                   extra_metadata={**recipe.metadata(), "model_size": model_size},
                   sentences=sentences, fixed_params=fixed)
    return result, time.time() - start
