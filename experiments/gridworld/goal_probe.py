"""Does a grid-world denoiser read which object the instruction names? Measured on its own
training distribution, with no planner in between: a training batch of the recipe (the mixture
of P-MO2G, MO1G and 1O1G examples, as trained), each clean plan noised to timestep t, and the
denoiser's one-step estimate of the clean plan; a row counts the examples whose estimated goal
(and P-MO2G sub-goal: the reference) peaks on the cell the expert's plan marks. At the last
timestep the estimate sees only the map and the instruction, so a denoiser that does not read
the names picks among the visible objects.

``python -m experiments.goal_probe --checkpoint DIR [DIR ...]``; a diagnostic (what
docs/results.md reports of the features models), not a result: the batch is a training batch.
"""
from __future__ import annotations

import argparse
from typing import Sequence

import numpy as np

from experiments.gridworld.spec import SPECS
from experiments.harness import cli, core as harness

TIMESTEPS = (99, 80, 60)
BATCH = 256
GOAL, SUBGOAL = 1, 2
"""The generated channels of the goal and the sub-goal (after the path, channel 0)."""


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="python -m experiments.goal_probe",
        description="How often a grid-world denoiser's one-step estimate puts the goal (and "
                    "P-MO2G's sub-goal, the reference) on the expert's cell, on one training "
                    "batch of its own recipe noised to each timestep: whether it reads which "
                    "object the instruction names, with no planner in between.")
    p.add_argument("--checkpoint", nargs="+", required=True, metavar="DIR",
                   help="grid-world denoiser checkpoints (token ids or pretrained features)")
    p.add_argument("--timesteps", default=",".join(map(str, TIMESTEPS)),
                   help="diffusion timesteps to noise to, comma-separated (default "
                        f"{','.join(map(str, TIMESTEPS))}; the last is the schedule's T - 1)")
    p.add_argument("--batch-size", type=int, default=BATCH,
                   help=f"examples (a multiple of the mixture's 64; default {BATCH})")
    p.add_argument("--seed", type=int, default=11, help="the batch's key (default 11)")
    p.add_argument("--json", metavar="PATH", help="write the rows as JSON")
    return p


def probe(denoiser, text: str, timesteps, batch_size: int, seed: int) -> list[dict]:
    """Rows (timestep, share of examples whose goal / sub-goal estimate peaks on the expert's
    cell, per setting of the mixture) for one denoiser reading ``text`` ("tokens" or
    "pretrained")."""
    import jax
    import jax.numpy as jnp

    from envs.gridworld.training import Recipe

    recipe = Recipe(text=text)
    batch = jax.jit(recipe.batch_fn(), static_argnums=1)(jax.random.PRNGKey(seed), batch_size)
    tokens = batch.tokens
    if text == "pretrained":
        from diffplan.instruction import assemble_batch

        tokens = assemble_batch(recipe.sentences(), tokens).astype(jnp.float32)
    scale = batch_size // recipe.batch_multiple
    settings = np.concatenate([[s] * (n * scale) for s, n in recipe.mixture])
    x0, c = batch.x0, denoiser.num_cond_channels
    rows = []
    for t in timesteps:
        ab = denoiser.schedule.alphas_cumprod[t]
        noise = jax.random.normal(jax.random.PRNGKey(t), x0[..., c:].shape)
        xt = x0.at[..., c:].set(jnp.sqrt(ab) * x0[..., c:] + jnp.sqrt(1 - ab) * noise)
        out = denoiser.apply_fn(denoiser.params, xt, jnp.full((batch_size,), t), tokens)
        if denoiser.prediction == "eps":
            out = (xt[..., c:] - jnp.sqrt(1 - ab) * out) / jnp.sqrt(ab)
        peak = lambda a, ch: np.asarray(a[..., ch]).reshape(batch_size, -1).argmax(1)
        goal = peak(x0[..., c:], GOAL) == peak(out, GOAL)
        sub = peak(x0[..., c:], SUBGOAL) == peak(out, SUBGOAL)
        row = {"t": int(t)}
        for setting, _ in recipe.mixture:
            row[f"goal {setting}"] = float(100 * goal[settings == setting].mean())
        row["reference p_mo2g"] = float(100 * sub[settings == "p_mo2g"].mean())
        rows.append(row)
    return rows


def main(argv: Sequence[str] | None = None) -> dict:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        timesteps = tuple(int(t) for t in args.timesteps.split(","))
    except ValueError:
        parser.error(f"--timesteps must be comma-separated integers, got {args.timesteps!r}")
    cli.check_at_least(parser, "--batch-size", args.batch_size, 64)
    if args.batch_size % 64:
        parser.error(f"--batch-size must be a multiple of 64, got {args.batch_size}")
    cli.check_output_file(parser, "--json", args.json)
    from diffplan.jax_cache import enable_compilation_cache
    from experiments.harness.text import reads_features

    enable_compilation_cache()
    result = {"batch_size": args.batch_size, "seed": args.seed, "checkpoints": {}}
    for checkpoint in args.checkpoint:
        denoiser = harness.load_checked(checkpoint, "python -m experiments.compile_p_mo2g "
                                                    "--train", SPECS["p_mo2g"].mismatch)
        steps = len(denoiser.schedule.alphas_cumprod)
        for t in timesteps:
            if not 0 <= t < steps:
                harness.fail(f"timestep {t} is outside the schedule's 0..{steps - 1}")
        text = "pretrained" if reads_features(denoiser) else "tokens"
        rows = probe(denoiser, text, timesteps, args.batch_size, args.seed)
        result["checkpoints"][checkpoint] = {"text": text, "rows": rows}
        print(f"\n{checkpoint} ({text}): % of {args.batch_size} training examples whose "
              "one-step estimate peaks on the expert's cell")
        keys = list(rows[0])
        print("  ".join(f"{k:>16}" for k in keys))
        for row in rows:
            print("  ".join(f"{row[k]:>16.1f}" if k != "t" else f"{row[k]:>16d}" for k in keys))
    print("legend: t = the timestep the clean plan was noised to (the last: pure noise); goal "
          "<setting> = % of that setting's examples whose goal estimate peaks on the goal cell; "
          "reference p_mo2g = % of P-MO2G examples whose sub-goal estimate peaks on the "
          "reference")
    if args.json:
        cli.write_json(args.json, result)
    return result
