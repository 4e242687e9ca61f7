"""Checks shared by the experiment CLIs, run on the arguments before any work starts, so that
a user error ends in one line on stderr and exit code 2 (argparse's ``parser.error``), never in
a traceback after minutes of evaluation."""
from __future__ import annotations

import argparse
import os


def _writable_dir(path: str) -> bool:
    """True if ``path`` is a directory we can write into, or could be created as one."""
    path = os.path.abspath(path)
    while not os.path.exists(path):
        parent = os.path.dirname(path)
        if parent == path:
            return False
        path = parent
    return os.path.isdir(path) and os.access(path, os.W_OK | os.X_OK)


def check_output_file(parser: argparse.ArgumentParser, flag: str, path: str | None,
                      suffix: str | None = None) -> None:
    """``path`` (the value of ``flag``) can be written as a file: not a directory, its
    directory writable or creatable, and ending in ``suffix`` if given."""
    if path is None:
        return
    if not path or path.endswith(os.sep):
        parser.error(f"{flag} needs a file path, got {path!r}")
    if os.path.isdir(path):
        parser.error(f"{flag} {path!r} is a directory; give a file path")
    if suffix and not path.endswith(suffix):
        parser.error(f"{flag} {path!r} must end in {suffix}")
    if os.path.exists(path) and not os.access(path, os.W_OK):
        parser.error(f"{flag} {path!r} exists and is not writable")
    if not _writable_dir(os.path.dirname(os.path.abspath(path))):
        parser.error(f"{flag} {path!r}: its directory cannot be created or written")


def check_output_dir(parser: argparse.ArgumentParser, flag: str, path: str | None) -> None:
    """``path`` (the value of ``flag``) is, or can be created as, a writable directory."""
    if path is None:
        return
    if not path:
        parser.error(f"{flag} needs a directory path")
    if os.path.exists(path) and not os.path.isdir(path):
        parser.error(f"{flag} {path!r} is a file; give a directory")
    if not _writable_dir(path):
        parser.error(f"{flag} {path!r} cannot be created or written")


def check_at_least(parser: argparse.ArgumentParser, flag: str, value, minimum) -> None:
    """``value`` (of ``flag``) is >= minimum (None: not given, nothing to check)."""
    if value is not None and value < minimum:
        parser.error(f"{flag} must be >= {minimum}, got {value}")


def only_with(parser: argparse.ArgumentParser, args: argparse.Namespace, needed: str,
              dependent_flags: dict[str, str]) -> None:
    """Flags that make sense only with ``--<needed>``: an error naming them when it is off.
    dependent_flags maps the attribute name (whose default is None) to the flag."""
    if getattr(args, needed.replace("-", "_")):
        return
    given = [flag for attr, flag in dependent_flags.items() if getattr(args, attr) is not None]
    if given:
        parser.error(f"{', '.join(given)} only make{'s' if len(given) == 1 else ''} sense with "
                     f"--{needed}")


def check_training_flags(parser: argparse.ArgumentParser, args: argparse.Namespace,
                         train_flags: dict[str, str]) -> None:
    """The flags of :func:`add_training_flags`: train_flags (attribute -> flag, e.g.
    --train-steps) only with --train, --checkpoint not with --train, counts in range."""
    only_with(parser, args, "train", train_flags)
    if args.train and args.checkpoint is not None:
        parser.error("--checkpoint and --train exclude each other: --train evaluates what it "
                     "trains (its output directory is --train-dir)")
    check_at_least(parser, "--train-steps", args.train_steps, 2)
    check_at_least(parser, "--checkpoint-every", args.checkpoint_every, 1)


def write_json(path: str, result: dict, announce: bool = True) -> None:
    """Writes ``result`` as indented JSON to ``path`` atomically (a temporary file in the same
    directory, then renamed: a crash mid-write never leaves half a file), creating the
    directory. A failure (full disk, permissions changed during the run) ends the program with
    one line on stderr, exit code 3; what was printed before stays on screen. In a
    multi-process run only process 0 writes (``processes.writes``)."""
    import json
    import sys
    import tempfile

    from experiments.harness.processes import writes

    if not writes():
        return

    directory = os.path.dirname(os.path.abspath(path))
    tmp = None
    try:
        os.makedirs(directory, exist_ok=True)
        with tempfile.NamedTemporaryFile("w", dir=directory, prefix=".tmp-",
                                         suffix=".json", delete=False) as f:
            tmp = f.name
            json.dump(result, f, indent=2)
            f.write("\n")
        os.replace(tmp, path)
    except OSError as e:
        print(f"error: cannot write {path}: {e.strerror or e}", file=sys.stderr)
        raise SystemExit(3)
    finally:
        if tmp is not None and os.path.exists(tmp):
            os.unlink(tmp)
    if announce:
        print(f"wrote {path}")


def atomic_file(path: str, write) -> None:
    """``write(tmp)`` writes the file, then it becomes ``path`` at once (a temporary name of
    the same suffix in the same directory, renamed): a process killed mid-write leaves no half
    file at ``path``."""
    directory, name = os.path.split(os.path.abspath(path))
    os.makedirs(directory, exist_ok=True)
    tmp = os.path.join(directory, f".tmp-{os.getpid()}-{name}")
    try:
        write(tmp)
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)


def add_training_flags(parser: argparse.ArgumentParser, *, training_name: str, served: str,
                       train_steps: int | str, checkpoint_every: int, model_sizes) -> None:
    """The flags of an experiment's ``--checkpoint`` / ``--train``: --checkpoint, --train,
    --train-dir, --train-steps, --train-seed, --checkpoint-every, --model-size (defaults None:
    :func:`only_with` tells which were given without --train). training_name: the shipped
    checkpoints/<name> and runs/<name>; served: what the one denoiser serves (for --help);
    train_steps: the default steps as --help states them."""
    parser.add_argument("--checkpoint", metavar="DIR",
                        help=f"evaluate this checkpoint (default: the shipped "
                             f"checkpoints/{training_name}, or the --train output)")
    parser.add_argument("--train", action="store_true",
                        help="train from scratch (resumes if --train-dir holds a checkpoint), "
                             "then evaluate the result")
    parser.add_argument("--train-dir", metavar="DIR", default=None,
                        help=f"training output directory (default runs/{training_name}; one "
                             f"denoiser serves {served})")
    parser.add_argument("--train-steps", type=int, default=None,
                        help=f"optimisation steps of --train (default {train_steps})")
    parser.add_argument("--train-seed", type=int, default=None,
                        help="training seed of --train (default 0)")
    parser.add_argument("--checkpoint-every", type=int, default=None, metavar="N",
                        help=f"--train writes a checkpoint every N steps (default "
                             f"{checkpoint_every}); a killed training resumes from the last one")
    parser.add_argument("--model-size", choices=sorted(model_sizes), default=None,
                        help="denoiser size for --train ('tiny' is for smoke tests; default "
                             "'default')")


def check_baselines(parser: argparse.ArgumentParser, names: str | None, known, root: str,
                    make: str = "python -m experiments.train_baselines --ship"):
    """The --baselines names (distinct, among known, each with a shipped checkpoint directory
    root/<name>, which the command ``make`` ships); () without the flag."""
    if names is None:
        return ()
    chosen = tuple(n.strip() for n in names.split(",") if n.strip())
    bad = [n for n in chosen if n not in known]
    if bad or not chosen or len(set(chosen)) != len(chosen):
        parser.error(f"--baselines must be distinct names of {','.join(known)}, got "
                     f"{names!r}")
    missing = [n for n in chosen if not os.path.isdir(os.path.join(root, n))]
    if missing:
        parser.error(f"no shipped baseline checkpoint for {','.join(missing)} under {root}: "
                     f"make them with `{make}`")
    return chosen


def add_tagger_flags(parser: argparse.ArgumentParser, *, seeds: str, steps: int, batch: int,
                     unit: str) -> None:
    """--seeds (one text tagger per seed) and --steps (per tagger, of batch ``unit``), with
    --json and --no-progress: the flags of the CLIs that train taggers."""
    parser.add_argument("--seeds", default=seeds,
                        help=f"comma-separated tagger seeds, one tagger each (default {seeds})")
    parser.add_argument("--steps", type=int, default=steps,
                        help=f"training steps of {batch} {unit} per tagger (default {steps})")
    parser.add_argument("--json", metavar="PATH", help="also write the results as JSON")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
