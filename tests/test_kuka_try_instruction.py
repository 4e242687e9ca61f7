"""`python -m experiments.try_instruction TEXT --world kuka`: one Kuka episode planned for a
user's own sentence with a denoiser on pretrained text features. The dispatcher picks the Kuka
parser for --world kuka (the grid one otherwise); a tiny checkpoint (2 training steps of the
tiny model: its plans mean nothing, only that everything runs is checked) plans an episode
end to end, printing one outcome line first and writing the figure, the GIF and the JSON; the
relations built are read from physical poses; the refusals are one line (exit 2)."""
from __future__ import annotations

import json
import os
import re

import numpy as np
import pytest

import kuka_fixtures as kf
from envs.kuka.sentences import FEATURE_TOKENS

pytestmark = pytest.mark.filterwarnings(kf.MJX_CAST_WARNING)

SENTENCE = "Put the red block on the blue block, please."


def run_exit(capsys, fn, argv, code: int = 2) -> str:
    """The last line on stderr of a CLI call that exits with ``code``, with no traceback."""
    with pytest.raises(SystemExit) as e:
        fn(argv)
    assert e.value.code == code
    err = capsys.readouterr().err
    assert "Traceback" not in err
    return err.strip().splitlines()[-1] if err.strip() else ""


@pytest.fixture(scope="module")
def checkpoint(tmp_path_factory) -> str:
    """A Kuka denoiser on pretrained text features: 2 steps of the tiny model."""
    from experiments.kuka import spec as ks

    out = tmp_path_factory.mktemp("kuka_try_instruction") / "run"
    ks.train_denoiser(str(out), steps=2, model_size="tiny", progress=False, text="pretrained")
    return str(out)


def test_the_dispatcher_picks_the_worlds_parser(capsys):
    from experiments.try_instruction import main, world_of

    assert [world_of(a) for a in (["x"], ["x", "--world", "kuka"], ["--world=kuka", "x"],
                                  ["x", "--world"])] == ["gridworld", "kuka", "kuka",
                                                         "gridworld"]
    with pytest.raises(SystemExit) as e:
        main(["--world", "kuka", "--help"])
    assert e.value.code == 0
    out = capsys.readouterr().out
    assert "--video" in out and "--task" in out and "--setting" not in out
    with pytest.raises(SystemExit) as e:
        main(["--help"])
    assert e.value.code == 0
    out = capsys.readouterr().out
    assert "--setting" in out and "--video" not in out
    assert "`--world kuka --help`" in " ".join(out.split())


def test_built_relations_are_read_from_physical_poses():
    from experiments.kuka.try_instruction import built_relations

    h = 0.03
    pos = np.array([[0.6, 0.0, h], [0.0, 0.6, h], [0.6, 0.0, 3 * h], [0.0, -0.6, h]])
    assert built_relations(pos, np.zeros(4, bool)) == ["blue on red"]
    assert built_relations(pos, np.array([False, False, True, False])) == []  # held: not on
    assert built_relations(pos * [1, 1, 0] + [0, 0, h], np.zeros(4, bool)) == []  # floor


def test_one_line_refusals(checkpoint, capsys, monkeypatch, tmp_path):
    from experiments.kuka import spec as ks
    from experiments.try_instruction import main

    kuka = ["--world", "kuka", "--checkpoint", checkpoint]
    assert "empty" in run_exit(capsys, main, ["   "] + kuka)
    assert f"over the limit of {FEATURE_TOKENS}" in run_exit(capsys, main, ["red " * 90] + kuka)
    monkeypatch.setattr(ks, "CHECKPOINT_ROOT", str(tmp_path))
    err = run_exit(capsys, main, [SENTENCE, "--world", "kuka"])
    assert err.startswith("error: no Kuka denoiser on pretrained text features")
    assert ("`python -m experiments.kuka_stacking --train --text pretrained`" in err
            and "--checkpoint runs/kuka_pretrained" in err)
    err = run_exit(capsys, main, [SENTENCE, "--world", "kuka", "--checkpoint",
                                  str(tmp_path / "nowhere")])
    assert "kuka_stacking --train --text pretrained" in err
    err = run_exit(capsys, main, [SENTENCE, "--world", "kuka", "--checkpoint",
                                  os.path.join("checkpoints", "kuka")])
    assert "reads token ids" in err
    assert "must end in .gif" in run_exit(capsys, main, [SENTENCE] + kuka + ["--video", "a.png"])


def test_plans_a_users_sentence_end_to_end(checkpoint, tmp_path, capsys):
    from PIL import Image

    from envs.kuka import scene
    from experiments.kuka.try_instruction import outcome_line
    from experiments.try_instruction import main

    figure, video, out_json = (str(tmp_path / name) for name in ("o.png", "o.gif", "o.json"))
    result = main([SENTENCE, "--world", "kuka", "--task", "stacking", "--seed", "3",
                   "--checkpoint", checkpoint, "--figure", figure, "--video", video,
                   "--json", out_json])
    out = capsys.readouterr().out.splitlines()
    assert out[0] == outcome_line(result)
    assert out[0].startswith(("success", "failure")) and "denoiser calls" in out[0]
    assert "(on-the-fly, stacking seed 3 episode 0); built: " in out[0]
    assert result["episode_instruction"] in out[1]
    assert os.path.getsize(figure) > 0
    with Image.open(video) as gif:
        assert gif.n_frames > 1
    written = json.loads(open(out_json).read())
    assert written == json.loads(json.dumps(result))
    assert {"text", "seed", "episode", "success", "built"} <= set(written)
    assert (written["text"], written["seed"], written["episode"]) == (SENTENCE, 3, 0)
    assert written["relations"] == 1 and written["tower"] in (True, False)
    names = "|".join(scene.BLOCK_NAMES)
    assert all(re.fullmatch(f"({names}) on ({names})", r) for r in written["built"])
    assert 1 <= written["moves"] <= 6
    assert written["denoiser_calls"] == 10 * written["moves"]  # a plan of 10 steps per move
