"""The paper release's P-MO2G denoiser timed beside ours, in the same run.

    pip install -e ".[anchors]"     # torch (CPU) and diffusers, only for this benchmark
    python -m experiments.bench_release [--json bench_release.json]

The release (github.com/joeyy5588/planning-as-inpainting, config/grid_sequence.yaml) plans
P-MO2G with a diffusers ``UNet2DConditionModel``: sample 16 x 16, 514 input channels (CLIP
features of the cells), 2 output channels, blocks (256, 512, 1024) with cross-attention at the
first two levels and the middle, cross-attention dim 1024, mish, 8 norm groups; 50 DDIM steps
per plan, batches of 64, up to 10 plans per batch in its evaluation. It is built here with that
configuration and random weights (what is timed does not depend on the weights), with random
text states of 77 tokens. Rows: its forward at batch 64, a 50-step plan, and its evaluation
procedure per episode (10 plans per batch of 64); ours: the shipped UNet's forward at batch 64,
a 10-step plan, and the measured jitted on-the-fly rollout per episode (64 P-MO2G episodes).
"""
from __future__ import annotations

import argparse
import os
import sys
import time

import numpy as np

REPO = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
RELEASE_CONFIG = dict(sample_size=16, in_channels=514, out_channels=2,
                      down_block_types=("CrossAttnDownBlock2D", "CrossAttnDownBlock2D",
                                        "DownBlock2D"),
                      up_block_types=("UpBlock2D", "CrossAttnUpBlock2D", "CrossAttnUpBlock2D"),
                      mid_block_type="UNetMidBlock2DCrossAttn",
                      block_out_channels=(256, 512, 1024), cross_attention_dim=1024,
                      act_fn="mish", norm_num_groups=8)
PLAN_STEPS_RELEASE, PLANS_PER_BATCH_RELEASE, BATCH = 50, 10, 64


def _median_time(fn, repeats: int) -> float:
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return float(np.median(times))


def release_rows(repeats: int, tokens: int = 77) -> list[dict]:
    import torch
    from diffusers import UNet2DConditionModel

    torch.manual_seed(0)
    model = UNet2DConditionModel(**RELEASE_CONFIG).eval()
    params = sum(p.numel() for p in model.parameters())
    x = torch.randn(BATCH, 514, 16, 16)
    text = torch.randn(BATCH, tokens, 1024)
    t = torch.full((BATCH,), 10, dtype=torch.long)

    def forward():
        with torch.no_grad():
            model(x, t, encoder_hidden_states=text)

    forward()  # warm-up
    fwd = _median_time(forward, repeats)
    plan = fwd * PLAN_STEPS_RELEASE
    return [
        {"method": "release forward, batch 64", "params": params, "seconds": fwd,
         "threads": torch.get_num_threads()},
        {"method": "release plan (50 DDIM steps), batch 64", "seconds": plan},
        {"method": "release evaluation per episode (10 plans / batch of 64)",
         "seconds": plan * PLANS_PER_BATCH_RELEASE / BATCH},
    ]


def our_rows(checkpoint: str, repeats: int) -> list[dict]:
    import jax
    import jax.numpy as jnp

    from diffplan import Planner, PlannerConfig, load_denoiser
    from diffplan.denoiser import count_params
    from diffplan.rollouts import rollout
    from experiments.gridworld.eval import eval_episodes
    from experiments.gridworld.spec import SPECS
    from experiments.harness.core import planner_keys

    den = load_denoiser(checkpoint)
    h, w, g = den.plan_shape
    x = jax.random.normal(jax.random.PRNGKey(0), (BATCH, h, w, den.num_cond_channels + g))
    x = x.at[..., 0].set(2.0)
    t = jnp.full((BATCH,), 10, jnp.int32)
    tok = jnp.ones((BATCH, 24), jnp.int32)
    forward = jax.jit(den.apply_fn)
    jax.block_until_ready(forward(den.params, x, t, tok))
    fwd = _median_time(lambda: jax.block_until_ready(forward(den.params, x, t, tok)), repeats)
    spec = SPECS["p_mo2g"]
    task = spec.task(den.num_gen_channels)
    planner = Planner(den, PlannerConfig(mode="on_the_fly", num_steps=10))
    episodes = eval_episodes(spec.grid_config(), BATCH, 3000)
    keys = planner_keys(3000, np.arange(BATCH))
    run = jax.jit(lambda p, k, e: rollout(task, p, k, e))
    jax.block_until_ready(run(planner, keys, episodes))
    episode_s = _median_time(lambda: jax.block_until_ready(run(planner, keys, episodes)),
                             max(1, repeats // 2)) / BATCH
    return [
        {"method": "ours forward, batch 64", "params": count_params(den.params),
         "seconds": fwd},
        {"method": "ours plan (10 DDIM steps), batch 64", "seconds": fwd * 10},
        {"method": "ours on-the-fly evaluation per episode (jitted rollout, batch 64)",
         "seconds": episode_s},
    ]


def main(argv=None) -> int:
    from experiments.harness import cli

    p = argparse.ArgumentParser(prog="python -m experiments.bench_release",
                                description=__doc__.split("\n\n")[0])
    p.add_argument("--checkpoint", default=os.path.join(REPO, "checkpoints", "compile_gridworld"),
                   help="our denoiser (default: the shipped one)")
    p.add_argument("--repeats", type=int, default=3, help="timed calls per row (median)")
    p.add_argument("--json", metavar="PATH", help="write the rows as JSON")
    args = p.parse_args(argv)
    cli.check_at_least(p, "--repeats", args.repeats, 1)
    cli.check_output_file(p, "--json", args.json)
    try:
        import diffusers  # noqa: F401
        import torch  # noqa: F401
    except ImportError:
        print("error: bench_release needs torch and diffusers (the paper release's stack): "
              "pip install -e \".[anchors]\"", file=sys.stderr)
        return 2
    from diffplan.jax_cache import enable_compilation_cache
    enable_compilation_cache()
    rows = release_rows(args.repeats) + our_rows(args.checkpoint, args.repeats)
    release_ep = rows[2]["seconds"]
    ours_ep = rows[5]["seconds"]
    print(f"{'measure':<66} {'seconds':>10}")
    print("-" * 77)
    for r in rows:
        extra = f"  ({r['params'] / 1e6:.1f}M parameters)" if "params" in r else ""
        print(f"{r['method']:<66} {r['seconds']:>10.3f}{extra}")
    print("legend: seconds = the median of timed calls after a warm-up (no compilation), per "
          "call or per episode as the measure says; a plan's = its forward x its steps")
    print(f"release / ours per episode: {release_ep / ours_ep:.0f}x")
    result = {"experiment": "bench_release", "episodes": BATCH, "seed": 3000, "rows": rows,
              "release_over_ours_per_episode": release_ep / ours_ep,
              "release_config": {k: list(v) if isinstance(v, tuple) else v
                                 for k, v in RELEASE_CONFIG.items()}}
    if args.json:
        cli.write_json(args.json, result)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
