"""A wrong config file is one line naming each wrong key or value and what is allowed there, exit 2."""

from __future__ import annotations

import pytest

from occvo_cli.cli import main
from occvo_core import OccVOConfig
from occvo_core.errors import ConfigError

CASES = {  # file text -> what the one line must say
    '{gicp: {souce_pick: "uniform"}}': [
        "gicp.souce_pick: unknown key",
        "did you mean source_pick?",
        "coarse_iterations",
    ],
    '{gicp: {source_pick: "x"}}': ["gicp.source_pick: 'x' is not allowed", "'first', 'balanced' or 'uniform'"],
    "{gicp: {coarse_iterations: 0}}": ["gicp.coarse_iterations: 0 is not allowed", "greater than or equal to 1"],
    '{voxel_pfilter: {source_pick: "first"}}': ["voxel_pfilter.source_pick: unknown key", "belongs in gicp"],
    "{gicpp: {}}": ["gicpp: unknown key", "did you mean gicp?", "loop_closure"],
    "{gicp: 3}": ["gicp: must be a section of keys", "source_pick", "not 3"],
    "[1, 2]": ["must hold one object of keys, not a list"],
    "{gicp: ": ["not JSON5"],
}


@pytest.mark.parametrize("text", CASES)
def test_a_wrong_config_names_the_key_and_what_is_allowed(text, tmp_path, capfd):
    path = tmp_path / "occvo.json5"
    path.write_text(text)
    with pytest.raises(ConfigError) as caught:
        OccVOConfig.load(path)
    for phrase in CASES[text]:
        assert phrase in str(caught.value)
    assert main(["run", "--config", str(path), "--quiet"]) == 2
    out, err = capfd.readouterr()
    assert out == "" and err.count("\n") == 1 and "Traceback" not in err
    assert err.startswith(f"occvo run: error: {path}: ") and all(phrase in err for phrase in CASES[text])


def test_every_wrong_key_of_a_file_is_named(tmp_path):
    path = tmp_path / "occvo.json5"
    path.write_text('{gicp: {souce_pick: "x", coarse_iterations: -1}, loop_closure: {enabled: "maybe"}}')
    with pytest.raises(ConfigError) as caught:
        OccVOConfig.load(path)
    line = str(caught.value)
    assert "\n" not in line
    for key in ("gicp.souce_pick", "gicp.coarse_iterations", "loop_closure.enabled"):
        assert key in line


def test_a_missing_config_file_is_named(tmp_path):
    with pytest.raises(ConfigError, match="nowhere.json5: cannot be read"):
        OccVOConfig.load(tmp_path / "nowhere.json5")
