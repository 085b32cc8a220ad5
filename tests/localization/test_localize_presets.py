"""`mcl3d localize --preset`: the named settings, their layering under a config file and the
flags, the effective values in config.yaml and the name in summary.json."""

import json

import numpy as np
import pytest
import yaml
from typer.testing import CliRunner

from mcl3d.core import config as config_mod
from mcl3d.core.errors import ConfigError
from mcl3d.localization.pipeline import LocalizeConfig
from mcl3d.localization.presets import LOCALIZE_PRESETS, localize_preset

localize_world = pytest.importorskip("support.localize_world")

TIGHT = "0.05 0.05 0.02 0.573 0.573 1.146"  # m, deg


@pytest.fixture(scope="module")
def data(tmp_path_factory, backend):
    from mcl3d.core import runtime

    runtime.init(backend)
    d = tmp_path_factory.mktemp("presets")
    localize_world.write_log(d / "room.mcap", 10)
    localize_world.save_room_map(d / "room.tsdf", 0.1)
    return d


def invoke(*args):
    from mcl3d.cli import app

    return CliRunner().invoke(app, [str(a) for a in args])


def _get(cfg: dict, dotted: str):
    for part in dotted.split("."):
        cfg = cfg[part]
    return cfg


def test_every_preset_is_documented_and_valid():
    for name, make in LOCALIZE_PRESETS.items():
        assert make.__doc__ and len(make.__doc__) > 80, name
        config_mod.load(LocalizeConfig, None, preset=localize_preset(name))
    assert localize_preset("default") == {}


def test_unknown_preset_names_the_choices():
    with pytest.raises(ConfigError, match="default, paper") as exc:
        localize_preset("papr")
    assert exc.value.setting == "preset"


def test_a_config_file_and_flags_override_the_preset(tmp_path):
    """Defaults < preset < config file < flags, key by key."""
    path = tmp_path / "c.yaml"
    path.write_text("localizer:\n  sensor:\n    sigma_m: 0.2\n")
    cfg = config_mod.load(LocalizeConfig, path, {"localizer.estimate.mean": "cluster"},
                          preset=localize_preset("paper"))
    loc = cfg.localizer
    assert loc.sensor.sigma_m == 0.2  # the file
    assert loc.estimate.mean == "cluster"  # the flag
    assert loc.sensor.model == "paper" and loc.resample.ess_threshold == 1.0  # the preset
    assert config_mod.load(LocalizeConfig, None) == LocalizeConfig()  # no preset: defaults


def test_paper_preset_end_to_end(data, tmp_path):
    """Tracking from the first ground-truth pose with the paper's model and estimate: the
    run succeeds, config.yaml holds the paper's values and the estimate stays on the truth."""
    out = tmp_path / "out"
    r = invoke("localize", data / "room.mcap", "--map", data / "room.tsdf", "-o", out,
               "--preset", "paper", "--init", "gt", "--init-std", TIGHT, "--particles", 2000,
               "--seed", 4, "--backend", "cpu")
    assert r.exit_code == 0, r.output
    saved = yaml.safe_load((out / "config.yaml").read_text())
    for key, value in localize_preset("paper").items():
        assert _get(saved, key) == value, key
    summary = json.loads((out / "summary.json").read_text())
    assert summary["preset"] == "paper"
    assert summary["ate_all"]["translation_rmse_m"] < 0.1


def test_paper_preset_global_init_runs(data, tmp_path):
    """Global initialization under the paper preset (uniform 6-DoF particles over all free
    space, no search aids) runs through and writes every scan."""
    out = tmp_path / "g"
    r = invoke("localize", data / "room.mcap", "--map", data / "room.tsdf", "-o", out,
               "--preset", "paper", "--particles", 3000, "--seed", 2, "--max-scans", 4,
               "--backend", "cpu")
    assert r.exit_code == 0, r.output
    assert np.loadtxt(out / "trajectory.tum").shape == (4, 8)
    summary = json.loads((out / "summary.json").read_text())
    assert summary["preset"] == "paper" and summary["height_band_m"] is None


def test_unknown_preset_is_one_line_and_exit_1(data, tmp_path):
    from mcl3d.cli import _with_flag

    r = invoke("localize", data / "room.mcap", "--map", data / "room.tsdf", "-o",
               tmp_path / "o", "--preset", "fast", "--backend", "cpu")
    assert r.exit_code == 1
    line = _with_flag(r.exception)
    assert "unknown preset 'fast'" in line and "default, paper" in line and "--preset" in line
    assert "\n" not in line
    assert not (tmp_path / "o").exists()
