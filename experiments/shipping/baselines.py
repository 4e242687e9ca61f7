"""Ships the trained baselines: exports the runs of ``experiments.train_baselines`` as small
evaluation checkpoints (``diffplan.baselines.policies.export_params``) under
``checkpoints/baselines/<name>/`` (per-setting models in ``<name>/<setting>/``; the Kuka
world's under ``checkpoints/baselines/kuka/<name>/``) and writes a NOTE.md beside each: what
the baseline is, the command, seed, steps, training time, and its rows of the results JSONs
(``experiments.baselines_eval``'s, or a Kuka CLI's).
"""
from __future__ import annotations

import json
import os
import shutil

from diffplan.baselines.policies import DD_PARTS, METHOD_NAMES, export_params
from diffplan.checkpoint import read_metadata
from envs.gridworld.training import TRAINING_MIXTURE
from experiments.gridworld.eval import format_table

PAPER_SETTINGS = tuple(setting for setting, _ in TRAINING_MIXTURE)
"""The settings of per-setting models (those the baselines are evaluated in)."""

DESCRIPTIONS = {
    "bc": "Behaviour cloning (the paper's BC, appendix): two 3x3 conv layers of 16 channels, "
          "two dense layers of 40 units with the one-hot goal vector concatenated before the "
          "second, a 4-way move head; cross-entropy on the expert's moves along expert "
          "shortest paths; greedy.",
    "cql": "Conservative Q-learning (the paper's CQL, appendix): the BC network with 4 "
           "Q-values, trained offline on a 300k replay buffer of expert epsilon-greedy "
           "transitions (epsilon 1 -> 0.01 over 10k frames), reward minus the remaining "
           "instructed distance, double DQN + CQL(H) (alpha 1), gamma 0.99, tau 0.001, "
           "lr 1e-3; greedy.",
    "dd": "Decision-Diffuser-style planner (the paper's DD): diffusion over 16-frame "
          "trajectories of the flattened 256-cell grid with Diffuser's 1-D temporal UNet "
          "(widths 32/64) conditioned on the goal vector, frame 0 (the current "
          "observation) in-painted, an inverse dynamics MLP turning (frame 0, frame 1) into "
          "the move; re-plans every move. Beyond Decision Diffuser: the clean trajectory is "
          "predicted as frame 0 plus a change through a 256-unit head, the cells that change "
          "weigh 51x in the loss (see diffplan/baselines/dd.py for why).",
}



def shipped_parts(name: str, run_dir: str) -> tuple[str, ...]:
    """The parts of baseline name's runs under run_dir/<name> to export: "" (the one model),
    or the per-setting models' "<setting>" when run_dir/<name>/<setting> exist; each with
    "/diffusion" and "/inverse_dynamics" for dd."""
    settings = [s for s in PAPER_SETTINGS if os.path.isdir(os.path.join(run_dir, name, s))]
    return tuple(os.path.join(setting, part) for setting in settings or [""]
                 for part in (DD_PARTS if name == "dd" else ("",)))


def ship(names, run_dir, ship_dir, results, command, remarks=(), world: str = "gridworld"):
    """Exports run_dir/<name> (or its per-setting runs) to ship_dir/<name> and writes its
    NOTE.md (world: whose baselines they are); what ship_dir/<name> held before is
    replaced."""
    for name in names:
        summaries = []
        out = os.path.join(ship_dir, name)
        if os.path.isdir(out):
            shutil.rmtree(out)  # an export, remade from the runs below
        for part in shipped_parts(name, run_dir):
            src, dst = (os.path.join(root, name, part) for root in (run_dir, ship_dir))
            os.makedirs(dst, exist_ok=True)
            export_params(src, dst, ema=(name == "dd" and part.endswith("diffusion")))
            summaries.append((part.rstrip("/"), _summary(src)))
        write_note(out, name, METHOD_NAMES[name], summaries, results, command, remarks, world)
        print(f"shipped {out}")


def _summary(train_dir) -> dict:
    meta = read_metadata(train_dir)
    tc = meta.get("train_config", {})
    return {"step": meta.get("step"), **{k: tc.get(k) for k in ("seed", "batch_size", "lr")},
            "wall_time": meta.get("wall_time", float("nan")), "model_config": meta["model_config"]}


KUKA_DESCRIPTIONS = {
    "bc": "Behaviour cloning in the Kuka world (the paper's Table 2 BC, appendix): the CompILE "
          "network (two 3x3 conv layers of 16 channels, two dense layers of 40 units with the "
          "multi-hot constraint vector concatenated before the second) on the planner's "
          "condition channels, the task decomposed into single pick-and-place moves: two "
          "576-way heads choose the pick cell and the place cell; cross-entropy on the "
          "training expert's moves in the states between placements; greedy; executed by the "
          "same primitive and physics, the block carried around the base "
          "(envs/kuka/baselines.py).",
    "cql": "Conservative Q-learning in the Kuka world (the paper's Table 2 CQL, appendix): the "
           "same network with one Q-value per cell (576), a move decided in two steps (the "
           "cell to pick from, then, told which block that took, the cell to place on); "
           "trained offline on a 300k buffer of epsilon-greedy transitions around the "
           "training expert (epsilon 1 -> 0.01 over 10k frames) made without physics in the "
           "expert's training states, reward minus the distance (m) from the chosen cell to "
           "the current target (the block to pick, then the place), double DQN + CQL(H) "
           "(alpha 1), gamma 0.99, tau 0.001, lr 1e-3; greedy; executed by the same "
           "primitive and physics (envs/kuka/baselines.py).",
    "dd": "Decision-Diffuser-style planner in the Kuka world (the paper's Table 2 DD): "
          "diffusion over 4-frame trajectories of block states (the four blocks' centres, 12 "
          "values: the blocks now and after each of the training expert's next placements, "
          "made without physics) with Diffuser's 1-D temporal UNet (widths 32/64, kernel 3) "
          "conditioned on the multi-hot constraint vector (dropped for 10% of the examples: "
          "classifier-free guidance), frame 0 (the observed block poses) in-painted; an "
          "inverse dynamics MLP turns (frame 0, frame 1) into the pick cell and the place "
          "cell (two 576-way heads); re-plans after every placement; executed by the same "
          "primitive and physics (envs/kuka/baselines.py).",
}
"""What each Kuka baseline is (its NOTE.md's first paragraph)."""
KUKA_DATA = ("- trained on the Kuka denoiser's task specs (the four Table 2 columns, canonical "
             "and training-paraphrase instructions, the same share each; envs.kuka.training."
             "SPECS), states drawn as the denoiser's training draws them")


def _kuka_results(name, method, result) -> list[str]:
    """The NOTE.md lines of a Kuka CLI's results (its rows of the baseline)."""
    from experiments.kuka.tables import format_table as kuka_table

    rows = [r for r in result["rows"] if r["method"].startswith(method + ",")]
    if not rows:
        return []
    seeds = ",".join(map(str, result.get("seeds", [result["seed"]])))
    who = f"--policy {name}" if result.get("policy") == name else f"--baselines {name}"
    settle = result.get("settle_seconds", 0)
    return [f"`python -m experiments.{result['experiment']} {who} --episodes "
            f"{result['episodes']} --seeds {seeds} --language {result['language']} --settle "
            f"{settle:g}` ({result.get('machine', '')}; strict SR on the poses after "
            f"{settle:g} s at rest):", "", "```",
            kuka_table(rows), "```", ""]


def _grid_results(name, method, result) -> list[str]:
    """The NOTE.md lines of an experiments.baselines_eval result (its rows of the baseline)."""
    rows = [r for r in result["rows"] if r["method"] == method]
    if not rows:
        return []
    seeds = ",".join(map(str, result.get("seeds", [result["seed"]])))
    dd_note = (f"; {result.get('dd_num_steps')} DDIM steps per move, guidance "
               f"{result.get('dd_guidance')}" if name == "dd" else "")
    lines = [f"`python -m experiments.baselines_eval --episodes {result['episodes']} "
             f"--seeds {seeds}` ({result.get('machine', '')}{dd_note}):", "", "```"]
    lines += ["setting  " + format_table(rows).splitlines()[0]]
    for r in rows:
        lines.append(f"{r['setting']:<8} " + format_table([r]).splitlines()[2])
    return lines + ["```", ""]


def write_note(out_dir, name, method, summaries, results, command, remarks=(),
               world: str = "gridworld"):
    """out_dir/NOTE.md of a shipped baseline: what it is, how it was made (summaries: (part,
    _summary) of each exported run), what it achieved (its rows of the results JSONs)."""
    kuka = world == "kuka"
    lines = [f"# {name}" + (" (Kuka)" if kuka else ""), "",
             (KUKA_DESCRIPTIONS if kuka else DESCRIPTIONS)[name], "", "## How it was made", "",
             f"- command: `{command}`"]
    total = 0.0
    for part, s in summaries:
        label = f"{part}: " if part else ""
        lines.append(f"- {label}training seed {s['seed']}; {s['step']} steps of batch "
                     f"{s['batch_size']}, lr {s['lr']}; model {json.dumps(s['model_config'])}; "
                     f"{s['wall_time'] / 60:.1f} min of optimisation on a 2-core CPU")
        total += s["wall_time"]
    per_setting = any(part.split("/")[0] in PAPER_SETTINGS for part, _ in summaries)
    mixture = ", ".join(f"{count} {setting}" for setting, count in TRAINING_MIXTURE)
    data = (KUKA_DATA if kuka else
            "- one model per setting (in <setting>/), each trained on its setting's examples "
            "only" if per_setting else
            f"- one model for the three settings (trained on the mixture: {mixture} examples "
            f"per {sum(c for _, c in TRAINING_MIXTURE)})")
    lines += [f"- training time in all: {total / 60:.1f} min (optimisation, as logged; data "
              "collection and compilation come on top)", data,
              "- exported with `python -m experiments.train_baselines --ship`",
              *[f"- {r}" for r in remarks], "",
              "## What it achieved (in percent, measured on executed trajectories)", ""]
    for result in results:
        lines += (_kuka_results if kuka else _grid_results)(name, method, result)
    with open(os.path.join(out_dir, "NOTE.md"), "w") as f:
        f.write("\n".join(lines))
