"""experiments.kuka_role_probe: its labels (against the templates, read in plain Python), its
refusal of phrasings that would spoil the probe, and one tiny end-to-end run."""
import json

import jax
import numpy as np
import pytest

from envs.kuka import grammar
from experiments.kuka import role_probe as probe


def test_roles_follow_the_slots_of_each_template():
    templates = probe.compiled(grammar.RELATION_TEMPLATES)
    tokens, roles, named = map(np.asarray, probe.role_batch(jax.random.PRNGKey(3), templates, 64))
    for t, r, m in zip(tokens, roles, named):
        sentence = grammar.decode(t)
        # Which template it is: the one that renders to it with the two blocks named.
        names = [w for w in sentence.split() if w in grammar.BLOCK_NAMES]
        assert len(names) == 2 and names[0] != names[1]
        matches = [k for k, text in enumerate(grammar.RELATION_TEMPLATES)
                   if any(text.replace("{top}", a).replace("{bottom}", b) == sentence
                          for a, b in (names, names[::-1]))]
        assert len(matches) == 1
        text = grammar.RELATION_TEMPLATES[matches[0]]
        first_is_top = text.index("{top}") < text.index("{bottom}")
        ids = np.flatnonzero(m)
        assert len(ids) == 2
        assert list(r[ids]) == ([0, 1] if first_is_top else [1, 0])
        assert not r[~m].any()


@pytest.mark.parametrize("template, needle", [
    ("Set the {bottom} block beside the {top} block.", "'beside'"),
    ("Set the {bottom} block under the {top} block.", "a development phrasing"),
    ("Put the {top} block on the {top} block.", "exactly once"),
])
def test_phrasings_that_would_spoil_the_probe_are_refused(template, needle):
    with pytest.raises(ValueError, match=needle):
        probe.check_extra([template])


def test_a_tiny_run_writes_its_table_and_json(tmp_path, capsys):
    path = tmp_path / "probe.json"
    extra = "Set the {bottom} block below the {top} block."
    result = probe.main(["--seeds", "0", "--steps", "3", "--extra", extra, "--json", str(path),
                         "--no-progress"])
    assert json.loads(path.read_text()) == json.loads(json.dumps(result))
    (row,) = result["rows"]
    assert result["extra"] == [extra]
    for key in ["training"] + [f"#{k}" for k in grammar.RELATION_SPLIT.unseen]:
        # A rate is a count of probe.EVAL_SENTENCES sentences read right, in percent.
        count = row[key] * probe.EVAL_SENTENCES / 100.0
        assert 0 <= round(count) <= probe.EVAL_SENTENCES
        assert count == pytest.approx(round(count), abs=1e-6), (key, row[key])
    out = capsys.readouterr().out
    assert "#11" in out and "taggers that read every development phrasing" in out


def test_broad_trains_on_the_grammar_extras_once():
    extras = [grammar.RELATION_TEMPLATES[k] for k in grammar.EXTRA]
    result = probe.main(["--seeds", "0", "--steps", "2", "--broad", "--extra", extras[0],
                         "--no-progress"])
    assert result["extra"] == extras
