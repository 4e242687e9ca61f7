"""envs.gridworld.export (DESIGN contract 1) and envs.gridworld.render."""
from __future__ import annotations

import os
import pathlib
import subprocess
import sys

import jax
import numpy as np
import pytest
from test_gridworld_bfs import oracle_bfs
from test_gridworld_episode import compass_sector

from envs.gridworld import export, grammar, render
from envs.gridworld.config import make_config

ROOT = pathlib.Path(__file__).resolve().parents[1]
N, SEED, SMALL_CHUNK = 40, 3, 16

CONTRACT = {  # key -> (dtype kind / dtype, shape given N and the 16 x 16 grid)
    "grid": (np.dtype(np.int8), (N, 16, 16)),
    "agent": (np.dtype(np.int32), (N, 2)),
    "target": (np.dtype(np.int32), (N, 2)),
    "reference": (np.dtype(np.int32), (N, 2)),
    "expert_path": (np.dtype(bool), (N, 16, 16)),
    "expert_length": (np.dtype(np.int32), (N,)),
    "visible0": (np.dtype(bool), (N, 16, 16)),
    "instruction": ("U", (N,)),
    "object_names": ("U", (len(grammar.OBJECT_NAMES),)),
}


@pytest.fixture(scope="module")
def p_mo2g_small_chunks():
    """p_mo2g episodes 0..N-1 of SEED generated in chunks of 16 (16 + 16 + 8 of a full 16)."""
    return export.export_episodes(make_config("p_mo2g"), N, SEED, chunk_size=SMALL_CHUNK)


def check_contract(arrays):
    assert set(arrays) == set(CONTRACT)
    for key, (dtype, shape) in CONTRACT.items():
        a = arrays[key]
        assert isinstance(a, np.ndarray), key
        if dtype == "U":
            assert a.dtype.kind == "U", (key, a.dtype)
        else:
            assert a.dtype == dtype, (key, a.dtype)
        assert a.shape == shape, (key, a.shape)
    assert export.validate_export(arrays) == N


def test_contract_keys_dtypes_shapes(p_mo2g_small_chunks):
    check_contract(p_mo2g_small_chunks)
    assert list(p_mo2g_small_chunks["object_names"]) == list(grammar.OBJECT_NAMES)


def test_chunk_size_independent_and_equal_to_generate_batch(p_mo2g_small_chunks, gen_batch):
    """Chunks of 16 == one chunk of 64 truncated == episodes 0..N-1 of generate_batch."""
    one_chunk = export.export_episodes(make_config("p_mo2g"), N, SEED)  # chunk 64 for n = 40
    eps, visible0 = gen_batch("p_mo2g", SEED)
    direct = export.export_arrays(jax.tree.map(lambda a: a[:N], eps), make_config("p_mo2g"),
                                  visible0[:N])
    for key in CONTRACT:
        np.testing.assert_array_equal(p_mo2g_small_chunks[key], one_chunk[key], err_msg=key)
        np.testing.assert_array_equal(p_mo2g_small_chunks[key], direct[key], err_msg=key)


def test_deterministic_per_seed(p_mo2g_small_chunks):
    config = make_config("p_mo2g")
    again = export.export_episodes(config, N, SEED, chunk_size=SMALL_CHUNK)
    for key in CONTRACT:
        np.testing.assert_array_equal(p_mo2g_small_chunks[key], again[key], err_msg=key)
    other = export.export_episodes(config, N, SEED + 1, chunk_size=SMALL_CHUNK)
    assert (other["grid"] != again["grid"]).any((1, 2)).mean() > 0.9
    # A prefix of an export is the export of the prefix.
    prefix = export.export_episodes(config, 10, SEED, chunk_size=SMALL_CHUNK)
    for key in CONTRACT:
        expected = again[key] if key == "object_names" else again[key][:10]
        np.testing.assert_array_equal(prefix[key], expected, err_msg=key)


def test_content_is_consistent(p_mo2g_small_chunks):
    """visible0 is the radius-6 Chebyshev square around the agent, the target is hidden and the
    reference visible, the expert path is a shortest path through the reference, and the
    instruction names the objects on the grid."""
    a = p_mo2g_small_chunks
    rows = np.arange(16)[:, None]
    cols = np.arange(16)[None, :]
    for i in range(N):
        agent, target, ref = (tuple(a[k][i]) for k in ("agent", "target", "reference"))
        square = (np.abs(rows - agent[0]) <= 6) & (np.abs(cols - agent[1]) <= 6)
        np.testing.assert_array_equal(a["visible0"][i], square)
        assert not a["visible0"][i][target] and a["visible0"][i][ref]
        path = a["expert_path"][i]
        assert path[agent] and path[ref] and path[target]
        assert not (path & (a["grid"][i] == -1)).any()
        passable = a["grid"][i] != -1
        length = int(a["expert_length"][i])
        assert length == oracle_bfs(passable, ref)[agent] + oracle_bfs(passable, target)[ref]
        assert path.sum() <= length + 1
        words = grammar.split_words(a["instruction"][i])
        names = a["object_names"]
        assert names[a["grid"][i][target] - 1] in words and names[a["grid"][i][ref] - 1] in words
        grammar.encode(a["instruction"][i])  # every word is in the vocabulary


def test_settings_without_reference(gen_batch):
    for setting in ("1o1g", "mo1g"):
        config = make_config(setting)
        eps, visible0 = gen_batch(setting, 0)
        arrays = export.export_arrays(eps, config, visible0)
        assert export.validate_export(arrays) == len(eps.agent)
        assert (arrays["reference"] == -1).all()
        assert arrays["visible0"].all()  # fully observable
        if setting == "1o1g":
            assert ((arrays["grid"] > 0).sum((1, 2)) == 1).all()
        # Recomputing visible0 with env.reset gives the same.
        again = export.export_arrays(eps, config)
        np.testing.assert_array_equal(again["visible0"], arrays["visible0"])


def test_save_load_round_trip(p_mo2g_small_chunks, tmp_path):
    out = tmp_path / "episodes.data"  # written exactly there, no ".npz" appended
    export.save_npz(out, p_mo2g_small_chunks)
    assert out.exists() and not (tmp_path / "episodes.data.npz").exists()
    assert [p.name for p in tmp_path.iterdir()] == ["episodes.data"]  # no temporary left over
    with np.load(out, allow_pickle=False) as data:
        assert set(data.files) == set(CONTRACT)
        loaded = {k: data[k] for k in data.files}
    check_contract(loaded)
    for key in CONTRACT:
        np.testing.assert_array_equal(loaded[key], p_mo2g_small_chunks[key])


@pytest.mark.parametrize("kwargs, message", [
    (dict(n=0), "n must be in 1"),
    (dict(n=-5), "n must be in 1"),
    (dict(n=2.5), "n must be an integer"),
    (dict(n=True), "n must be an integer"),
    (dict(seed=-1), "seed must be in 0"),
    (dict(seed=2**32), "seed must be in 0"),
    (dict(chunk_size=0), "chunk_size must be in 1"),
])
def test_export_episodes_bad_arguments(kwargs, message):
    args = dict(config=make_config("p_mo2g"), n=4, seed=0) | kwargs
    with pytest.raises(ValueError, match=message):
        export.export_episodes(**args)


def test_export_episodes_needs_a_config():
    with pytest.raises(ValueError, match="GridConfig"):
        export.export_episodes("p_mo2g", 4, 0)


def test_validate_export_reports_mismatches(p_mo2g_small_chunks):
    bad = dict(p_mo2g_small_chunks)
    bad["grid"] = bad["grid"].astype(np.int32)
    bad["extra"] = np.zeros(3)
    del bad["visible0"]
    with pytest.raises(ValueError) as info:
        export.validate_export(bad)
    assert "grid: dtype int32" in str(info.value) and "extra" in str(info.value)
    assert "visible0" in str(info.value)


def test_cli_help_lists_every_flag(capsys):
    with pytest.raises(SystemExit) as info:
        export.main(["--help"])
    assert info.value.code == 0
    text = capsys.readouterr().out
    for flag in ("--setting", "--n", "--seed", "--out", "--figures", "--num-figures",
                 "--paraphrase", "--language", "--chunk-size", "--no-compress", "--quiet", "--cache-dir"):
        assert flag in text
    for setting in ("1o1g", "mo1g", "p_mo2g"):
        assert setting in text


@pytest.mark.parametrize("argv, message", [
    (["--setting", "p_mo2g", "--n", "0", "--out", "{tmp}/x.npz"], "--n must be >= 1"),
    (["--setting", "p_mo2g", "--n", "-3", "--out", "{tmp}/x.npz"], "--n must be >= 1"),
    (["--setting", "p_mo2g", "--n", "ten", "--out", "{tmp}/x.npz"], "invalid int value"),
    (["--setting", "mo2g", "--n", "3", "--out", "{tmp}/x.npz"], "invalid choice"),
    (["--setting", "p_mo2g", "--n", "3", "--out", "{tmp}/missing/x.npz"], "does not exist"),
    (["--setting", "p_mo2g", "--n", "3", "--out", "{tmp}"], "is a directory"),
    (["--setting", "p_mo2g", "--n", "3", "--seed", "-1", "--out", "{tmp}/x.npz"], "--seed"),
    (["--setting", "p_mo2g", "--n", "3", "--out", "{tmp}/x.npz", "--num-figures", "2"],
     "needs --figures"),
    (["--setting", "p_mo2g", "--n", "3", "--out", "{tmp}/x.npz", "--chunk-size", "0"],
     "--chunk-size"),
    (["--n", "3", "--out", "{tmp}/x.npz"], "--setting"),
])
def test_cli_bad_arguments(argv, message, tmp_path, capsys):
    with pytest.raises(SystemExit) as info:
        export.main([a.format(tmp=tmp_path) for a in argv])
    assert info.value.code == 2
    assert message in capsys.readouterr().err
    assert not (tmp_path / "x.npz").exists()


def test_cli_writes_the_contract(tmp_path, p_mo2g_small_chunks):
    """The CLI (a subprocess, tiny N, with --paraphrase and figures) writes the same episodes as
    export_episodes, phrased with several templates."""
    out = tmp_path / "p.npz"
    figures = tmp_path / "figs"
    env = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    result = subprocess.run(
        [sys.executable, "-m", "envs.gridworld.export", "--setting", "p_mo2g", "--n", str(N),
         "--seed", str(SEED), "--out", str(out), "--chunk-size", str(SMALL_CHUNK),
         "--paraphrase", "--figures", str(figures), "--num-figures", "2"],
        cwd=ROOT, env=env, capture_output=True, text=True, timeout=600)
    assert result.returncode == 0, result.stderr
    assert f"wrote {N} p_mo2g episodes" in result.stdout
    loaded = export.load_npz(out)
    check_contract(loaded)
    # --paraphrase changes the wording only: the same worlds, several templates.
    for key in CONTRACT:
        if key != "instruction":
            np.testing.assert_array_equal(loaded[key], p_mo2g_small_chunks[key], err_msg=key)
    templates = set()
    for i, text in enumerate(loaded["instruction"]):
        grid, ref, target = loaded["grid"][i], tuple(loaded["reference"][i]), tuple(
            loaded["target"][i])
        direction = compass_sector(ref, target)
        matches = [t for t in range(len(grammar.TEMPLATES["p_mo2g"]))
                   if grammar.render("p_mo2g", t, int(grid[ref]), int(grid[target]), direction)
                   == text]
        assert len(matches) == 1, text
        templates.add(matches[0])
    assert len(templates) >= 3
    pngs = sorted(figures.glob("*.png"))
    assert [p.name for p in pngs] == ["p_mo2g_00000.png", "p_mo2g_00001.png"]
    assert all(p.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" for p in pngs)


def test_render_episode_with_every_overlay(tmp_path, p_mo2g_small_chunks):
    a = p_mo2g_small_chunks
    rng = np.random.default_rng(0)
    plan = np.where(a["expert_path"][0], 1.0, -1.0) + rng.normal(0, 0.2, (16, 16))
    goal = -np.ones((16, 16))
    goal[tuple(a["target"][0])] = 1.0
    executed = np.array([a["agent"][0], a["agent"][0] + [0, 1], a["agent"][0] + [1, 1]])
    out = render.render_episode(
        tmp_path / "full.png", a["grid"][0], a["agent"][0], a["target"][0], a["reference"][0],
        a["instruction"][0], seen=a["visible0"][0], path=plan, goal=goal, executed=executed,
        title="test")
    assert out == tmp_path / "full.png"
    data = out.read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 10_000
    # On an existing Axes, with no reference and no overlays.
    from matplotlib.figure import Figure

    fig = Figure()
    ax = fig.add_subplot()
    assert render.render_episode(ax, a["grid"][1], a["agent"][1], a["target"][1], (-1, -1),
                                 "") is ax
    assert len(ax.texts) == (a["grid"][1] > 0).sum() + 1  # object labels + the name key
    with pytest.raises(ValueError, match="path must have the grid's shape"):
        render.render_episode(ax, a["grid"][1], a["agent"][1], a["target"][1], (-1, -1), "",
                              path=np.zeros((8, 8)))
    with pytest.raises(ValueError, match="Axes or a file path"):
        render.render_episode(3, a["grid"][1], a["agent"][1], a["target"][1], (-1, -1), "")


def test_short_names_are_unique():
    labels = render.short_names(grammar.OBJECT_NAMES)
    assert len(set(labels)) == len(labels)
    assert all(3 <= len(s) <= len(n) and n.startswith(s)
               for s, n in zip(labels, grammar.OBJECT_NAMES))
