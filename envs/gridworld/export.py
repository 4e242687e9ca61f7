"""Episode export (docs/DESIGN.md, contract 1): generated episodes as plain numpy arrays / an .npz file.

    python -m envs.gridworld.export --setting p_mo2g --n 2000 --seed 0 --out p_mo2g.npz \
        [--figures figs/ --num-figures 8] [--language canonical|paraphrased|unseen]

The file holds exactly these arrays (N episodes, a 16 x 16 grid by default):

    grid           int8  (N, H, W)  0 empty, -1 obstacle, k >= 1 object class object_names[k-1]
    agent          int32 (N, 2)     start cell (row, col); row 0 is north
    target         int32 (N, 2)     the instructed goal cell
    reference      int32 (N, 2)     the reference object's cell; (-1, -1) without one
    expert_path    bool  (N, H, W)  cells of a shortest obstacle-free 4-connected path from the
                                    agent through the reference (if any) to the target, ends
                                    included
    expert_length  int32 (N,)       number of moves of that path
    visible0       bool  (N, H, W)  the cells the agent sees at t=0
    instruction    str   (N,)       the instruction text
    object_names   str   (K,)       class names (grid value k is object_names[k-1])

Episode i is ``episode.generate(fold_in(PRNGKey(seed), i), config)``, exactly as in
``episode.generate_batch``: the output is deterministic per seed, any prefix is stable (the first
m episodes of an export of n > m are the export of m), and it does not depend on the chunk size
used to generate it.
"""
from __future__ import annotations

import argparse
import functools
import os
import pathlib
import sys
import tempfile
import time

import jax

from diffplan.jax_cache import enable_compilation_cache
from diffplan.language import LANGUAGES
import jax.numpy as jnp
import numpy as np

from envs.gridworld import env, episode, grammar
from envs.gridworld.config import SETTINGS, GridConfig, make_config

DEFAULT_CHUNK_SIZE = 4096
MAX_EPISODES = 2**31 - 1
"""Episode indices are int32 (as in episode.generate_batch)."""
MAX_SEED = 2**32 - 1

CONTRACT_DTYPES: dict[str, str] = {
    "grid": "int8",
    "agent": "int32",
    "target": "int32",
    "reference": "int32",
    "expert_path": "bool",
    "expert_length": "int32",
    "visible0": "bool",
    "instruction": "str",
    "object_names": "str",
}
"""The export's keys (exactly these) and dtypes ("str" = a numpy unicode array)."""


@functools.partial(jax.jit, static_argnames=("config", "chunk_size"))
def generate_chunk(key, start, config: GridConfig, chunk_size: int):
    """Episodes start .. start + chunk_size - 1 of ``key`` (episode i from fold_in(key, i)).

    Args:
      key: a PRNG key (uint32 (2,)); start: int32 () the first episode index (traced: one
      compilation serves every chunk); config, chunk_size: static.
    Returns:
      (Episode with a leading (chunk_size,) axis, visible0 bool (chunk_size, H, W)).
    """
    idx = start + jnp.arange(chunk_size, dtype=jnp.int32)
    keys = jax.vmap(lambda i: jax.random.fold_in(key, i))(idx)
    episodes = jax.vmap(episode.generate, in_axes=(0, None))(keys, config)
    visible0 = jax.vmap(lambda e: env.reset(e, config).seen)(episodes)
    return episodes, visible0


def decode_instructions(tokens) -> np.ndarray:
    """int32 (N, L) token ids -> str (N,) instructions (each distinct row decoded once)."""
    tokens = np.asarray(tokens)
    if tokens.ndim != 2:
        raise ValueError(f"tokens must be (N, L), got shape {tokens.shape}")
    if tokens.shape[0] == 0:
        return np.zeros((0,), dtype="<U1")
    unique, inverse = np.unique(tokens, axis=0, return_inverse=True)
    texts = np.array([grammar.decode(row) for row in unique])
    return texts[np.asarray(inverse).reshape(-1)]


def export_arrays(episodes: episode.Episode, config: GridConfig, visible0=None) -> dict:
    """A batch of episodes (leading axis N, jax or numpy) -> the contract's dict of numpy arrays.

    visible0: bool (N, H, W) cells seen at t=0; None recomputes it with env.reset."""
    if visible0 is None:
        visible0 = jax.vmap(lambda e: env.reset(e, config).seen)(episodes)
    ep = jax.tree.map(np.asarray, episodes)
    return {
        "grid": ep.grid.astype(np.int8),
        "agent": ep.agent.astype(np.int32),
        "target": ep.target.astype(np.int32),
        "reference": ep.reference.astype(np.int32),
        "expert_path": ep.expert_path.astype(bool),
        "expert_length": ep.expert_length.astype(np.int32),
        "visible0": np.asarray(visible0).astype(bool),
        "instruction": decode_instructions(ep.tokens),
        "object_names": np.array(grammar.OBJECT_NAMES),
    }


def _check_count(name: str, value, low: int, high: int) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
        raise ValueError(f"{name} must be an integer, got {value!r}")
    if not low <= value <= high:
        raise ValueError(f"{name} must be in {low}..{high}, got {value}")
    return int(value)


def export_episodes(config: GridConfig, n: int, seed: int, *, chunk_size: int = DEFAULT_CHUNK_SIZE,
                    progress: bool = False) -> dict:
    """Generates episodes 0..n-1 of ``seed`` and returns the contract's dict of numpy arrays.

    Generation runs in jitted chunks of ``min(chunk_size, next power of two >= n)`` episodes (the
    last chunk is generated in full and truncated, so there are few distinct compilations, which
    the persistent compilation cache then reuses across runs); the result does not depend on
    chunk_size. progress shows a tqdm bar over episodes.
    """
    if not isinstance(config, GridConfig):
        raise ValueError(f"config must be a GridConfig, got {type(config).__name__}")
    n = _check_count("n", n, 1, MAX_EPISODES)
    seed = _check_count("seed", seed, 0, MAX_SEED)
    chunk_size = _check_count("chunk_size", chunk_size, 1, MAX_EPISODES)
    chunk = min(chunk_size, 1 << (n - 1).bit_length())
    key = jax.random.PRNGKey(seed)
    parts = []
    from diffplan.progress import bar as progress_bar

    with progress_bar(total=n, unit="ep", desc=f"{config.setting} episodes",
                      disable=not progress, file=sys.stderr) as bar:
        for start in range(0, n, chunk):
            episodes, visible0 = generate_chunk(key, jnp.int32(start), config, chunk)
            count = min(chunk, n - start)
            episodes, visible0 = jax.tree.map(lambda a: np.asarray(a)[:count], (episodes,
                                                                               visible0))
            parts.append(export_arrays(episodes, config, visible0))
            bar.update(count)
    if len(parts) == 1:
        return parts[0]
    out = {k: np.concatenate([p[k] for p in parts]) for k in CONTRACT_DTYPES if k != "object_names"}
    out["object_names"] = parts[0]["object_names"]
    return out


def validate_export(arrays: dict, size: int | None = None) -> int:
    """Checks a dict (or loaded npz) against contract 1: exactly the keys, dtypes and shapes.

    Returns N; raises ValueError describing every mismatch."""
    errors = []
    keys = set(arrays.keys())
    if keys != set(CONTRACT_DTYPES):
        errors.append(f"keys {sorted(keys)} != {sorted(CONTRACT_DTYPES)}")
    n = np.asarray(arrays["grid"]).shape[0] if "grid" in keys else -1
    if size is None and "grid" in keys and np.asarray(arrays["grid"]).ndim == 3:
        size = np.asarray(arrays["grid"]).shape[1]
    shapes = {
        "grid": (n, size, size), "agent": (n, 2), "target": (n, 2), "reference": (n, 2),
        "expert_path": (n, size, size), "expert_length": (n,), "visible0": (n, size, size),
        "instruction": (n,),
    }
    for name, dtype in CONTRACT_DTYPES.items():
        if name not in keys:
            continue
        a = np.asarray(arrays[name])
        ok = a.dtype.kind == "U" if dtype == "str" else a.dtype == np.dtype(dtype)
        if not ok:
            errors.append(f"{name}: dtype {a.dtype}, expected {dtype}")
        if name in shapes and a.shape != shapes[name]:
            errors.append(f"{name}: shape {a.shape}, expected {shapes[name]}")
        if name == "object_names" and a.ndim != 1:
            errors.append(f"object_names: shape {a.shape}, expected (K,)")
    if errors:
        raise ValueError("not a valid episode export: " + "; ".join(errors))
    return n


def save_npz(path, arrays: dict, *, compress: bool = True) -> None:
    """Writes the arrays to exactly ``path`` (no '.npz' appended), atomically: via a temporary
    file in the same directory that replaces ``path`` only once fully written."""
    path = pathlib.Path(path)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as f:
            (np.savez_compressed if compress else np.savez)(f, **arrays)
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def load_npz(path) -> dict:
    """Reads an export back as a dict of numpy arrays (no pickle needed)."""
    with np.load(path, allow_pickle=False) as data:
        return {k: data[k] for k in data.files}


def _check_writable(path: pathlib.Path) -> str | None:
    """None if a file can be written at path, else the reason."""
    if path.is_dir():
        return f"--out {path} is a directory, expected a file path such as {path / 'episodes.npz'}"
    parent = path.parent
    if not parent.is_dir():
        return f"--out {path}: directory {parent} does not exist"
    try:
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=parent)
    except OSError as e:
        return f"--out {path}: cannot write in {parent} ({e.strerror})"
    os.close(fd)
    os.unlink(tmp)
    if path.exists() and not os.access(path, os.W_OK):
        return f"--out {path}: the existing file is not writable"
    return None


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="python -m envs.gridworld.export",
        description=(
            "Generate grid-world episodes and write them as an .npz file (docs/DESIGN.md, contract 1): "
            "grid int8 (N,H,W), agent/target/reference int32 (N,2) (reference (-1,-1) where the "
            "setting has none), expert_path bool (N,H,W), expert_length int32 (N,), visible0 bool "
            "(N,H,W), instruction str (N,), object_names str (K,). Episode i is generated from "
            "fold_in(PRNGKey(seed), i): the file is deterministic per seed and any prefix is "
            "stable."),
        formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    parser.add_argument("--setting", required=True, choices=SETTINGS,
                        help="1o1g: one object, no obstacles, fully observed; mo1g: several "
                             "objects and obstacles, fully observed; p_mo2g: partially observed, "
                             "a visible reference object and a target hidden at t=0; "
                             "p_mo2g_far: as p_mo2g, the target also hidden from the reference, "
                             "4-9 cells from it")
    parser.add_argument("--n", type=int, required=True, help="number of episodes (>= 1)")
    parser.add_argument("--seed", type=int, default=0, help=f"random seed (0..{MAX_SEED})")
    parser.add_argument("--out", required=True,
                        help="output .npz path, written exactly as given (its directory must "
                             "exist); replaced atomically once complete")
    parser.add_argument("--language", choices=LANGUAGES, default=None,
                        help="instruction phrasing: 'canonical' (template 0, default), "
                             "'paraphrased' (a training paraphrase) or 'unseen' (a held-out "
                             "phrasing no training batch contains)")
    parser.add_argument("--paraphrase", action="store_true",
                        help="the same as --language paraphrased")
    parser.add_argument("--figures", metavar="DIR", default=None,
                        help="also write PNG figures of the first --num-figures episodes to DIR "
                             "(created if missing)")
    parser.add_argument("--num-figures", metavar="K", type=int, default=None,
                        help="how many episode figures to write with --figures (default 8; at "
                             "most N)")
    parser.add_argument("--chunk-size", type=int, default=DEFAULT_CHUNK_SIZE,
                        help="episodes generated per jitted call; affects speed and memory only, "
                             "never the episodes")
    parser.add_argument("--no-compress", action="store_true",
                        help="write an uncompressed .npz (faster to write, larger)")
    parser.add_argument("--quiet", action="store_true", help="no progress bar or summary")
    parser.add_argument("--cache-dir", default=None,
                        help="JAX persistent compilation cache directory (default "
                             "$DIFFPLAN_JAX_CACHE or ~/.cache/diffplan-jax)")
    return parser


def main(argv=None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.n < 1:
        parser.error(f"--n must be >= 1, got {args.n}")
    if args.n > MAX_EPISODES:
        parser.error(f"--n must be <= {MAX_EPISODES}, got {args.n}")
    if not 0 <= args.seed <= MAX_SEED:
        parser.error(f"--seed must be in 0..{MAX_SEED}, got {args.seed}")
    if args.chunk_size < 1:
        parser.error(f"--chunk-size must be >= 1, got {args.chunk_size}")
    if args.num_figures is not None and args.figures is None:
        parser.error("--num-figures needs --figures DIR")
    out = pathlib.Path(args.out)
    problem = _check_writable(out)
    if problem:
        parser.error(problem)
    num_figures = 0
    if args.figures is not None:
        num_figures = 8 if args.num_figures is None else args.num_figures
        if num_figures < 0:
            parser.error(f"--num-figures must be >= 0, got {num_figures}")
        num_figures = min(num_figures, args.n)
        figures_dir = pathlib.Path(args.figures)
        if figures_dir.exists() and not figures_dir.is_dir():
            parser.error(f"--figures {figures_dir} exists and is not a directory")
        try:
            figures_dir.mkdir(parents=True, exist_ok=True)
        except OSError as e:
            parser.error(f"--figures {figures_dir}: cannot create the directory ({e.strerror})")
        if not os.access(figures_dir, os.W_OK):
            parser.error(f"--figures {figures_dir}: directory is not writable")

    enable_compilation_cache(args.cache_dir)
    if args.paraphrase and args.language not in (None, "paraphrased"):
        parser.error(f"--paraphrase contradicts --language {args.language}")
    language = "paraphrased" if args.paraphrase else (args.language or "canonical")
    config = make_config(args.setting, language=language)
    started = time.perf_counter()
    arrays = export_episodes(config, args.n, args.seed, chunk_size=args.chunk_size,
                             progress=not args.quiet and args.n > min(args.chunk_size, 4096))
    validate_export(arrays, config.size)
    save_npz(out, arrays, compress=not args.no_compress)
    if num_figures:
        from envs.gridworld import render

        render.save_export_figures(arrays, args.figures, num_figures, prefix=args.setting)
    if not args.quiet:
        seconds = time.perf_counter() - started
        print(f"wrote {args.n} {args.setting} episodes (seed {args.seed}) to {out} "
              f"({out.stat().st_size / 1e6:.1f} MB) in {seconds:.1f} s; mean expert length "
              f"{arrays['expert_length'].mean():.2f} moves"
              + (f"; {num_figures} figures in {args.figures}" if num_figures else ""))
    return 0


if __name__ == "__main__":
    sys.exit(main())
