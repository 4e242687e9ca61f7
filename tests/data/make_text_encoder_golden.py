"""Writes tests/data/text_encoder_golden.npz: the reference features of the shipped text encoder
(checkpoints/text_encoder), computed by Hugging Face transformers' BertModel in PyTorch, for
tests/test_pretrained_text.py. Run once, in a throwaway environment (never the project's: torch
and transformers are no dependency of diffplan):

    python3 -m venv /tmp/refvenv
    /tmp/refvenv/bin/pip install torch==2.13.0 transformers numpy safetensors
    HF_HUB_OFFLINE=1 /tmp/refvenv/bin/python tests/data/make_text_encoder_golden.py \
        --original DIR

The shipped float16 weights are loaded upcast to float32 (torch's dtype=float32), so the
fixture checks the JAX implementation, not the rounding. --original (optional) is a directory
with the upstream float32 files (the wheel's model.zip unpacked): the float16 artifact's
deviation from them is printed and stored as ``fp16_deviation``.

The npz: ``sentences`` str (N,); ``ids`` int32 (N, L) and ``mask`` bool (N, L) from
transformers' tokenizer (the same tokenizer.json), padded to L = 64; ``features`` float32
(N, L, 384), the last hidden state, 0 at padding; ``metadata`` a JSON string (command,
versions, the artifact's sha256, fp16_deviation).
"""
from __future__ import annotations

import argparse
import hashlib
import json
import pathlib
import sys

import numpy as np
import torch
import transformers

ROOT = pathlib.Path(__file__).resolve().parents[2]
ARTIFACT = ROOT / "checkpoints" / "text_encoder"
OUT = pathlib.Path(__file__).resolve().parent / "text_encoder_golden.npz"
LENGTH = 64
SENTENCES = (
    "Go to the apple.",
    "go to the apple then go north to find the pear",
    "Which object is the pear? Locate it, then proceed north-east of the chair.",
    "First go to the apple, then find the pear north of it.",
    "Could you place green over yellow?",
    "Place the green block on the yellow block, please.",
    "Stack blue on red, then green on blue.",
    "I want the red cube beneath the green cube.",
    "Build a tower of all four blocks.",
    "Move the yellow block so that it rests on the green block. Put the red block below the "
    "blue block. The green block should be beneath the red block.",
    "Under the blue block goes the yellow one.",
    "HEAD TO THE KEY!!!",
    "Find the ball; it's somewhere south-west of the box.",
    "Please, could you kindly walk over to the little wooden table near the door?",
    "zxqv blorf wug",
    "pear",
    "Put the café au lait mug on the naïve coaster.",
    "Go 3 steps east and 12 steps north.",
    "move   the\tred block\non the green block",
    "Antidisestablishmentarianism notwithstanding, stack them.",
    "Wohin? Gehe zum Apfel.",
    "把红色方块放在绿色方块上",
    "Stack 🍎 on 🍐 — quickly!",
    "(red) -> [green] {blue} <yellow> & 'quoted' \"words\"",
)


def sha256(path: pathlib.Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def features(directory: pathlib.Path, ids, mask) -> np.ndarray:
    model = transformers.BertModel.from_pretrained(str(directory), dtype=torch.float32)
    model.eval()
    assert all(p.dtype == torch.float32 for p in model.parameters())
    with torch.no_grad():
        out = model(input_ids=ids, attention_mask=mask,
                    token_type_ids=torch.zeros_like(ids)).last_hidden_state
    return (out * mask[..., None]).numpy().astype(np.float32)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--original", type=pathlib.Path, default=None,
                        help="a directory with the upstream float32 model files")
    args = parser.parse_args()
    torch.manual_seed(0)
    tokenizer = transformers.PreTrainedTokenizerFast(
        tokenizer_file=str(ARTIFACT / "tokenizer.json"))
    batch = tokenizer(list(SENTENCES), padding="max_length", max_length=LENGTH,
                      truncation=False, return_tensors="pt")
    ids, mask = batch["input_ids"], batch["attention_mask"]
    golden = features(ARTIFACT, ids, mask)
    deviation = None
    if args.original is not None:
        deviation = float(np.max(np.abs(features(args.original, ids, mask) - golden)))
        print(f"float16 artifact against the float32 original: max abs deviation {deviation:.4g}")
    metadata = {
        "command": "HF_HUB_OFFLINE=1 /tmp/refvenv/bin/python tests/data/"
                   "make_text_encoder_golden.py " + " ".join(sys.argv[1:]),
        "reference": "transformers.BertModel (PyTorch), float32, last_hidden_state * mask",
        "torch": torch.__version__, "transformers": transformers.__version__,
        "artifact_sha256": {name: sha256(ARTIFACT / name)
                            for name in ("config.json", "model.safetensors", "tokenizer.json")},
        "fp16_deviation": deviation,
    }
    np.savez_compressed(OUT, sentences=np.array(SENTENCES), ids=ids.numpy().astype(np.int32),
                        mask=mask.numpy().astype(bool), features=golden,
                        metadata=np.array(json.dumps(metadata)))
    print(f"wrote {OUT} ({OUT.stat().st_size / 1e6:.2f} MB), {len(SENTENCES)} sentences")


if __name__ == "__main__":
    main()
