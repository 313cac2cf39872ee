"""The users' door (issue 51): plugin files, their errors, and a fusion rule's own options."""

from __future__ import annotations

import dataclasses
import re
import textwrap
from pathlib import Path

import numpy as np
import pytest

from harness import methods
from harness.cli import main
from harness.config import plugins
from harness.config.assemble import load_config
from harness.errors import ConfigError
from harness.fusion import keys as fusion_keys
from harness.fusion.config import FusionConfig
from harness.fusion.fuse import loc_from_cover, register_fusion_rule

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture()
def clean():
    """The registries and the imported plugins as they were before the test."""
    regs = (methods.FUSION_RULES, methods.FUSION_OPTIONS, methods.METHOD_LABELS, plugins.LOADED)
    saved = [(d, dict(d)) for d in regs]
    yield
    for d, before in saved:
        d.clear()
        d.update(before)


def _plugin(tmp_path: Path, name: str, body: str) -> Path:
    path = tmp_path / name
    path.write_text(textwrap.dedent(body).lstrip())
    return path


RULE = """
    from dataclasses import dataclass

    import numpy as np

    from harness.fusion import register_fusion_rule


    @dataclass(frozen=True)
    class Scale:
        by: float = 1.0


    def scaled(cover, r, d, L, *, options):
        return cover.sum(1) * options.by


    register_fusion_rule("scaled", scaled, "scaled cover count", options=Scale)
"""


def _config(tmp_path: Path, extra: str) -> Path:
    text = (ROOT / "datasets" / "fixture.toml").read_text()
    text = text.replace('name = "fixture"\n', 'name = "fixture"\nplugins = ["scaled.py"]\n')
    conf = tmp_path / "c.toml"
    conf.write_text(text + textwrap.dedent(extra))
    return conf


def test_a_plugin_rule_and_its_table(tmp_path: Path, clean) -> None:
    _plugin(tmp_path, "scaled.py", RULE)
    conf = _config(
        tmp_path, '[fusion]\nmethods = ["rank_fusion", "scaled"]\n[fusion.scaled]\nby = 2.5\n'
    )
    cfg = load_config(conf)
    opts = cfg.fusion.options_of("scaled")
    assert opts.by == 2.5 and cfg.fusion.options_of("rank_fusion") is None
    cover = np.array([[1, 1, 0], [1, 0, 0]], bool)
    r, d, L = np.full(3, 0.5), np.ones(3), np.full(3, 4.0)
    assert np.allclose(loc_from_cover(cover, "scaled", r=r, d=d, L=L, options=opts), [5.0, 2.5])
    assert np.allclose(loc_from_cover(cover, "scaled", r=r, d=d, L=L), [2.0, 1.0])  # defaults
    # the table is part of the samples' key, and a config without one keeps the key of before
    other = dataclasses.replace(cfg, fusion=dataclasses.replace(cfg.fusion, options={}))
    assert fusion_keys.samples(cfg.fusion, cfg.splits, "r", "a") != fusion_keys.samples(
        other.fusion, other.splits, "r", "a"
    )
    assert "options" not in fusion_keys.samples(other.fusion, other.splits, "r", "a")[2]
    # loaded once per process: the same file again is no second registration
    assert load_config(conf).fusion.options_of("scaled").by == 2.5
    assert plugins.plugin_record()[-1]["path"] == str((tmp_path / "scaled.py").resolve())


@pytest.mark.parametrize(
    ("table", "says"),
    [("size = 2", "unknown key(s) ['size']"), ('by = "x"', "by")],
)
def test_a_rule_table_is_checked_like_every_table(
    tmp_path: Path, clean, table: str, says: str
) -> None:
    _plugin(tmp_path, "scaled.py", RULE)
    conf = _config(tmp_path, f'[fusion]\nmethods = ["scaled"]\n[fusion.scaled]\n{table}\n')
    with pytest.raises(ConfigError, match=re.escape(says)):
        load_config(conf)


def test_a_rule_named_like_a_fusion_key_or_with_bad_options_is_refused(clean) -> None:
    def flat(cover, r, d, L):
        return np.ones(len(cover))

    with pytest.raises(ValueError, match="a key of \\[fusion\\] itself"):
        register_fusion_rule("rrf_c", flat, "x")
    with pytest.raises(ValueError, match="options must be a dataclass"):
        register_fusion_rule("flat", flat, "flat", options=dict)
    assert "flat" not in methods.FUSION_RULES and FusionConfig().options_of("flat") is None


@pytest.mark.parametrize(
    ("body", "says"),
    [
        ("raise RuntimeError('no licence file')\n", "RuntimeError: no licence file"),
        ("import not_a_module_anywhere\n", "ModuleNotFoundError"),
        (
            "from harness.proposals import register_proposer\n"
            "register_proposer('edges', lambda rgb, cfg: None)\n",
            "ValueError",
        ),
    ],
)
def test_a_plugin_that_fails_is_one_error_line(
    tmp_path: Path, clean, capsys, body: str, says: str
) -> None:
    bad = _plugin(tmp_path, "bad.py", body)
    code = main(["--plugin", str(bad), "inspect", str(tmp_path)])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 1 and len(err) == 1, err
    assert err[0].startswith(f"ERROR: --plugin: plugin {bad}: ") and says in err[0], err[0]
    assert bad.resolve() not in plugins.LOADED


def test_a_missing_or_non_python_plugin_is_one_error_line(tmp_path: Path, clean, capsys) -> None:
    (tmp_path / "rule.txt").write_text("x = 1\n")
    for given in (tmp_path / "nope.py", tmp_path / "rule.txt"):
        assert main(["--plugin", str(given), "inspect", str(tmp_path)]) == 1
        err = capsys.readouterr().err.strip()
        assert err == f"ERROR: --plugin: plugin {given}: no such Python (.py) file"


def test_a_plugin_with_the_ray_executor_is_refused_before_any_work(
    tmp_path: Path, clean, capsys
) -> None:
    rule = _plugin(tmp_path, "scaled.py", RULE)
    out = tmp_path / "out"
    argv = ["--plugin", str(rule), "reproduce", "--config", str(ROOT / "datasets" / "fixture.toml")]
    assert main([*argv, "--out", str(out), "--executor", "ray"]) == 1
    err = capsys.readouterr().err
    assert "plugins run on the local executor only" in err and not out.exists()


def test_register_method_is_the_old_name_of_both_register_functions() -> None:
    """One vocabulary (issue 51): a fusion rule is registered with ``register_fusion_rule``, a
    proposer with ``register_proposer``; ``register_method``, their name before, still works."""
    from harness import fusion, proposals

    assert fusion.register_method is fusion.register_fusion_rule
    assert proposals.register_method is proposals.register_proposer
