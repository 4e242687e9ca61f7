"""Batched evaluation sweeps: many planner configurations, each one jitted, vmapped evaluation
over all its episodes, sharded across every JAX device.

    python -m experiments.sweep --config experiments/sweeps/p_mo2g_pareto.json --json s.json
    python -m experiments.sweep --setting p_mo2g --modes on_the_fly,warm_start \\
        --num-steps 10,3 --seed 2001 --episodes 200 --csv s.csv --figures figs/

A configuration holds the experiment CLIs' flags, with underscores: setting, checkpoint,
modes (one planning mode), num_steps, eta, warm_start_step, warm_num_steps, noise ("fresh" |
"episode"), replan ("always" | "on_change"; missing: the mode's own, as in the experiment
CLIs: on_the_fly "always", warm_start "on_change"), seed, episodes, batch_size (slots per
device of the re-planning modes' pool). ``--config FILE`` reads a JSON list of such objects
(missing keys take the experiment CLIs' defaults, listed below); on the command line,
comma-separated values give every combination.

Each configuration runs as one call of a jitted function over all its episodes: the
re-planning modes on a pool of slots per device (diffplan.rollout_stream), the others as one
diffplan.rollout batch; episodes are split over the devices (diffplan.sharding.per_device),
and each episode's result is the same on any number of devices (every episode has its own key
and planning sub-batches are of >= 16 episodes). Compiled functions are kept and reused by
configurations of the same shapes and planner settings (another seed or another checkpoint of
the same architecture costs no compilation); ``compile_seconds`` is the lowering and
compilation time of a configuration (0 when reused).

Rows: the metrics of contract 2 (SR, SR_ordered, GD, path P/R/F1, denoiser calls per episode,
seconds) plus compile_seconds and the configuration. ``--json``, ``--csv``, and ``--figures DIR``
(SR against denoiser calls per episode and against seconds, Pareto front marked).
"""
from __future__ import annotations

import argparse
import csv
import dataclasses
import itertools
import json
import os
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np

from experiments import cli
from experiments import compile_common as cc

_SPEC = cc.SPECS["p_mo2g"]
DEFAULTS = {"setting": "p_mo2g", "checkpoint": None, "modes": "on_the_fly",
            "num_steps": _SPEC.num_steps, "eta": _SPEC.eta,
            "warm_start_step": _SPEC.warm_start_step,
            "warm_num_steps": _SPEC.warm_num_steps or _SPEC.num_steps,
            "noise": "fresh" if _SPEC.fresh_noise else "episode", "replan": None,
            "seed": cc.DEFAULT_EVAL_SEED, "episodes": 1000, "batch_size": _SPEC.eval_batch}
"""The experiment CLIs' defaults (replan None: the mode's own trigger, cc.MODE_REPLAN)."""
TYPES = {"setting": str, "checkpoint": str, "modes": str, "num_steps": int, "eta": float,
         "warm_start_step": int, "warm_num_steps": int, "noise": str, "replan": str,
         "seed": int, "episodes": int, "batch_size": int}
CHOICES = {"setting": tuple(cc.SPECS), "noise": ("fresh", "episode"),
           "replan": ("always", "on_change")}


class SweepError(ValueError):
    """A configuration that cannot run (the message says which and why)."""


def normalise(raw: dict, index: int) -> dict:
    """A configuration with defaults filled in and every value checked."""
    if not isinstance(raw, dict):
        raise SweepError(f"configuration {index} must be a JSON object, got {raw!r}")
    unknown = sorted(set(raw) - set(DEFAULTS))
    if unknown:
        raise SweepError(f"configuration {index}: unknown keys {unknown}; allowed: "
                         f"{sorted(DEFAULTS)}")
    config = dict(DEFAULTS, **raw)
    for key, kind in TYPES.items():
        value = config[key]
        if value is None and key in ("checkpoint", "replan"):
            continue
        if kind is float and isinstance(value, int) and not isinstance(value, bool):
            value = float(value)
        if not isinstance(value, kind) or isinstance(value, bool):
            raise SweepError(f"configuration {index}: {key} must be {kind.__name__}, got "
                             f"{value!r}")
        config[key] = value
    for key, allowed in CHOICES.items():
        if config[key] is None and key == "replan":
            continue
        if config[key] not in allowed:
            raise SweepError(f"configuration {index}: {key} must be one of {allowed}, got "
                             f"{config[key]!r}")
    from diffplan.planner import MODES
    if config["modes"] not in MODES:
        raise SweepError(f"configuration {index}: modes must be one planning mode of {MODES}, "
                         f"got {config['modes']!r}")
    if config["replan"] is None:
        config["replan"] = cc.SPECS[config["setting"]].replan_of(config["modes"])
    for key, minimum in (("episodes", 1), ("batch_size", 1), ("seed", 0), ("num_steps", 1),
                         ("warm_num_steps", 1), ("warm_start_step", 0)):
        if config[key] < minimum:
            raise SweepError(f"configuration {index}: {key} must be >= {minimum}, got "
                             f"{config[key]}")
    if not 0 <= config["eta"] <= 10:
        raise SweepError(f"configuration {index}: eta must be in [0, 10], got {config['eta']}")
    try:
        planner_config(config)
    except ValueError as e:
        raise SweepError(f"configuration {index}: {e}") from e
    return config


def spec_of(config: dict) -> cc.ExperimentSpec:
    return dataclasses.replace(
        cc.SPECS[config["setting"]], num_steps=config["num_steps"],
        warm_start_step=config["warm_start_step"], warm_num_steps=config["warm_num_steps"],
        fresh_noise=config["noise"] == "fresh", eta=config["eta"], replan=config["replan"])


def planner_config(config: dict):
    return spec_of(config).planner_config(config["modes"])


def expand(values: dict) -> list[dict]:
    """Every combination of comma-separated command-line values."""
    keys = [k for k in DEFAULTS if values.get(k) is not None]
    lists = [[v.strip() for v in str(values[k]).split(",")] for k in keys]
    out = []
    for combo in itertools.product(*lists):
        config = {}
        for key, value in zip(keys, combo):
            kind = TYPES[key]
            try:
                config[key] = kind(value)
            except ValueError as e:
                raise SweepError(f"--{key.replace('_', '-')}: {value!r} is not a "
                                 f"{kind.__name__}") from e
        out.append(config)
    return out


class Runner:
    """Runs configurations, keeping compiled evaluations for reuse."""

    def __init__(self, mesh=None, progress: bool = True):
        from diffplan import sharding as shd
        self.mesh = shd.data_mesh() if mesh is None else mesh
        self.devices = self.mesh.size
        self.progress = progress
        self._compiled = {}
        self._denoisers = {}

    def denoiser(self, checkpoint: str, spec, index: int):
        if checkpoint not in self._denoisers:
            from diffplan.checkpoint import CorruptCheckpointError
            try:
                self._denoisers[checkpoint], _ = cc.load_model(checkpoint)
            except (FileNotFoundError, CorruptCheckpointError, ValueError) as e:
                raise SweepError(f"configuration {index}: checkpoint {checkpoint}: {e}") from e
        den = self._denoisers[checkpoint]
        try:
            spec.planner_config("on_the_fly").check_schedule(den.schedule.num_train_steps)
            spec.planner_config("warm_start").check_schedule(den.schedule.num_train_steps)
        except ValueError as e:
            raise SweepError(f"configuration {index}: {e}") from e
        return den

    def _function(self, task, mode: str, slots: int):
        from diffplan import sharding as shd
        from diffplan.rollouts import rollout, rollout_stream
        from experiments.progress import RELAY

        def evaluate(planner, token, keys, episodes):
            if mode in cc.STREAM_MODES:
                part = token + jax.lax.axis_index(shd.DATA_AXIS) if self.devices > 1 else token
                return rollout_stream(task, planner, keys, episodes, slots, on_move=RELAY,
                                      token=part)
            return rollout(task, planner, keys, episodes)

        return shd.per_device(evaluate, self.mesh, num_replicated=2)

    def run(self, config: dict, index: int, episodes_cache: dict,
            trajectories: str | None = None) -> dict:
        from tqdm import tqdm

        from diffplan.planner import Planner
        from experiments.progress import PARTS, RELAY

        spec = spec_of(config)
        checkpoint = config["checkpoint"] or spec.default_checkpoint()
        den = self.denoiser(checkpoint, spec, index)
        task = spec.task(den.num_gen_channels)
        n, seed = config["episodes"], config["seed"]
        key = (config["setting"], n, seed)
        if key not in episodes_cache:
            episodes_cache[key] = cc.eval_episodes(spec.grid_config(), n, seed)
        episodes = episodes_cache[key]
        padded = -(-n // self.devices) * self.devices
        idx = np.arange(padded) % n
        chunk = jax.tree.map(lambda x: x[idx], episodes)
        root = jax.random.fold_in(jax.random.PRNGKey(seed), cc.ROLLOUT_STREAM)
        keys = jax.vmap(lambda i: jax.random.fold_in(root, i))(jnp.asarray(idx))
        planner = Planner(den, planner_config(config))
        slots = min(config["batch_size"], padded // self.devices)
        from diffplan import sharding as shd
        chunk = shd.shard_batch(chunk, self.mesh)
        keys = shd.shard_batch(keys, self.mesh)
        planner_placed = shd.replicate(planner, self.mesh)
        cache_key = (task, planner.config, padded, slots, config["modes"],
                     jax.tree.structure(planner_placed),
                     tuple((x.shape, str(x.dtype)) for x in jax.tree.leaves(planner_placed)))
        bar = tqdm(total=n, desc=f"[{index + 1}] {label(config)} seed {seed}", unit="ep",
                   disable=not self.progress,
                   file=sys.stderr, leave=True, dynamic_ncols=True)
        token = RELAY.attach(bar)
        try:
            compile_seconds = 0.0
            if cache_key not in self._compiled:
                fn = self._function(task, config["modes"], slots)
                t0 = time.time()
                self._compiled[cache_key] = fn.lower(
                    planner_placed, jnp.int32(0), keys, chunk).compile()
                compile_seconds = time.time() - t0
            t0 = time.time()
            out = jax.device_get(self._compiled[cache_key](
                planner_placed, jnp.int32(token * PARTS), keys, chunk))
            seconds = time.time() - t0
        finally:
            RELAY.detach(token)
            bar.update(n - bar.n)
            bar.close()
        out = jax.tree.map(lambda x: np.asarray(x)[:n], out)
        if trajectories:
            cc.write_trajectories(os.path.join(trajectories, f"config_{index:03d}.npz"), out,
                                  episodes, spec.grid_config())
        row = cc.metrics_row(cc.METHOD_NAMES[config["modes"]], out, episodes, seconds,
                             spec.grid_config().has_reference)
        row.update(compile_seconds=compile_seconds, wall_seconds=seconds + compile_seconds,
                   devices=self.devices, **{k: config[k] for k in DEFAULTS if k != "checkpoint"},
                   checkpoint=os.path.relpath(checkpoint, cc.REPO_ROOT))
        return row


CSV_FIELDS = ("setting", "modes", "num_steps", "eta", "warm_num_steps", "warm_start_step",
              "noise", "replan", "seed", "episodes", "checkpoint", "SR", "SR_ordered", "GD",
              "path_precision", "path_recall", "path_f1", "denoiser_calls_per_episode",
              "seconds", "compile_seconds", "wall_seconds", "devices")


def write_csv(path: str, rows) -> None:
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    with open(path, "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=CSV_FIELDS, extrasaction="ignore")
        writer.writeheader()
        for row in rows:
            writer.writerow({k: row.get(k, "") for k in CSV_FIELDS})


def pareto_front(xs, ys) -> list[int]:
    """Indices of the points no other point beats (lower x and higher y), by increasing x."""
    order = sorted(range(len(xs)), key=lambda i: (xs[i], -ys[i]))
    front, best = [], -np.inf
    for i in order:
        if ys[i] > best:
            front.append(i)
            best = ys[i]
    return front


def label(row) -> str:
    extra = (f" {row['warm_num_steps']}/{row['warm_start_step']}" if row["modes"] ==
             "warm_start" else f" {row['num_steps']}")
    return (f"{row['modes']}{extra}" + (" on_change" if row["replan"] == "on_change" else "")
            + (f" eta{row['eta']:g}" if row["eta"] else ""))


def write_figures(out_dir: str, rows) -> list[str]:
    """Two PNGs (x: denoiser calls per episode, then evaluation seconds), each with two panels:
    SR and path F1 against the cost, every configuration labelled, the Pareto front drawn
    (when every SR ties, as on P-MO2G, the path F1 panel still separates the modes)."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    os.makedirs(out_dir, exist_ok=True)
    paths = []
    for x_key, x_label, name in (("denoiser_calls_per_episode", "denoiser calls per episode",
                                  "pareto_calls.png"),
                                 ("seconds", "seconds (evaluation, no compilation)",
                                  "pareto_seconds.png")):
        xs = [r[x_key] for r in rows]
        fig, axes = plt.subplots(1, 2, figsize=(11, 4.6))
        for ax, (y_key, y_label) in zip(axes, (("SR", "SR (%)"), ("path_f1", "path F1 (%)"))):
            ys = [r[y_key] for r in rows]
            ax.scatter(xs, ys, color="#3060c0", zorder=3)
            order = sorted(range(len(rows)), key=lambda i: xs[i])
            for rank, i in enumerate(order):  # alternate label offsets: fewer overlaps
                ax.annotate(label(rows[i]), (xs[i], ys[i]), fontsize=6.5,
                            xytext=(3, 4 if rank % 2 == 0 else -9),
                            textcoords="offset points")
            front = pareto_front(xs, ys)
            ax.plot([xs[i] for i in front], [ys[i] for i in front], color="#d04020",
                    zorder=2, marker="o", markerfacecolor="none", label="Pareto front")
            ax.set_xscale("log")
            ax.set_xlabel(x_label)
            ax.set_ylabel(y_label)
            lo, hi = min(ys), max(ys)
            pad = max(0.5, 0.1 * (hi - lo))
            ax.set_ylim(lo - pad, hi + pad)
            ax.grid(alpha=0.3)
            ax.legend(fontsize=8, loc="lower right")
        fig.suptitle(f"success against cost ({len(rows)} configurations)", fontsize=10)
        fig.tight_layout()
        path = os.path.join(out_dir, name)
        fig.savefig(path, dpi=110)
        plt.close(fig)
        paths.append(path)
    return paths


def format_rows(rows) -> str:
    head = (f"{'#':>3} {'configuration':<34} {'seed':>5} {'eps':>5} {'SR':>7} {'SR_ord':>7} "
            f"{'F1':>6} {'calls':>7} {'sec':>7} {'compile':>7}")
    lines = [head, "-" * len(head)]
    for i, r in enumerate(rows):
        lines.append(f"{i + 1:>3} {label(r):<34} {r['seed']:>5} {r['episodes']:>5} "
                     f"{r['SR']:>7.2f} {r.get('SR_ordered', float('nan')):>7.2f} "
                     f"{r['path_f1']:>6.1f} {r['denoiser_calls_per_episode']:>7.1f} "
                     f"{r['seconds']:>7.1f} {r['compile_seconds']:>7.1f}")
    return "\n".join(lines)


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python -m experiments.sweep",
                                description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter,
                                epilog="Configuration keys and defaults: " + json.dumps(DEFAULTS))
    p.add_argument("--config", metavar="FILE",
                   help="a JSON list of configurations (objects with the keys below)")
    for key, default in DEFAULTS.items():
        p.add_argument(f"--{key.replace('_', '-')}", default=None, metavar="V[,V...]",
                       help=f"{key} (comma-separated values: every combination; default "
                            f"{default!r}; not with --config)")
    p.add_argument("--json", metavar="PATH", help="write the rows (contract 2 layout)")
    p.add_argument("--csv", metavar="PATH", help="write the rows as CSV")
    p.add_argument("--figures", metavar="DIR", help="write the Pareto figures")
    p.add_argument("--trajectories", metavar="DIR",
                   help="write each configuration's executed trajectories and episodes "
                        "(contract 2's format) to DIR/config_NNN.npz")
    p.add_argument("--no-progress", action="store_true", help="hide progress bars")
    return p


def main(argv=None) -> dict:
    from diffplan.jax_cache import enable_compilation_cache

    parser = build_parser()
    args = parser.parse_args(argv)
    given = {k: getattr(args, k) for k in DEFAULTS if getattr(args, k) is not None}
    cli.check_output_file(parser, "--json", args.json)
    cli.check_output_file(parser, "--csv", args.csv, suffix=".csv")
    cli.check_output_dir(parser, "--figures", args.figures)
    cli.check_output_dir(parser, "--trajectories", args.trajectories)
    try:
        if args.config:
            if given:
                parser.error(f"--config excludes the per-key flags ({', '.join(given)})")
            try:
                with open(args.config) as f:
                    raw = json.load(f)
            except (OSError, json.JSONDecodeError) as e:
                parser.error(f"--config {args.config!r} cannot be read as JSON: {e}")
            if not isinstance(raw, list) or not raw:
                parser.error(f"--config {args.config!r} must hold a non-empty JSON list")
        else:
            raw = expand(given)
        configs = [normalise(c, i) for i, c in enumerate(raw)]
    except SweepError as e:
        parser.error(str(e))
    enable_compilation_cache()
    runner = Runner(progress=not args.no_progress)
    for i, config in enumerate(configs):  # every checkpoint loads before any work
        try:
            runner.denoiser(config["checkpoint"] or spec_of(config).default_checkpoint(),
                            spec_of(config), i)
        except SweepError as e:
            parser.error(str(e))
    rows, episodes_cache = [], {}
    from tqdm import tqdm
    outer = tqdm(total=len(configs), desc="configurations", unit="cfg", file=sys.stderr,
                 disable=args.no_progress, leave=True, position=0)
    for i, config in enumerate(configs):
        rows.append(runner.run(config, i, episodes_cache, args.trajectories))
        outer.update(1)
    outer.close()
    result = {"experiment": "sweep", "episodes": int(sum(c["episodes"] for c in configs)),
              "seed": configs[0]["seed"], "devices": runner.devices,
              "machine": f"{os.cpu_count()} CPU cores, jax {jax.__version__} on "
                         f"{jax.devices()[0].platform}", "rows": rows}
    print(format_rows(rows))
    if args.json:
        cli.write_json(args.json, result)
    if args.csv:
        write_csv(args.csv, rows)
        print(f"wrote {args.csv}")
    if args.figures:
        for path in write_figures(args.figures, rows):
            print(f"wrote {path}")
    return result


if __name__ == "__main__":
    main()
