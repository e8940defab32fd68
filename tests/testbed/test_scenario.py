"""Scenario files (testbed.scenario): a scenario built on another (``base``)."""

import pytest

from bodyslam.errors import ConfigError
from testbed.scenario import load_scenario

EXAM_PACE = ["camera.width=320", "camera.height=320", "motion.mean_step_m=0.0006", "motion.mean_roll_deg=3.0",
             "motion.mean_tilt_deg=2.5", "motion.offset_std_frac=0.05", "sequence.frames=400"]


def _without_labels(scn: dict) -> dict:
    return {k: v for k, v in scn.items() if k not in ("name", "description", "_origin")}


def test_realistic_exam_is_realistic_at_the_exam_pace():
    """docs/RESULTS.md's slow runs were `realistic` with these overrides; the named scenario is the same world."""
    own, by_hand = load_scenario("realistic_exam"), load_scenario("realistic", EXAM_PACE)
    assert _without_labels(own) == _without_labels(by_hand)
    assert own["name"] == "realistic_exam" and "exam's pace" in own["description"]
    # the base's tables are kept where the scenario does not touch them, and its own keys win inside a table
    assert own["motility"] == load_scenario("realistic")["motility"]
    assert own["camera"]["width"] == 320 and own["camera"]["fov_deg"] == load_scenario("realistic")["camera"]["fov_deg"]


def test_a_users_scenario_file_builds_on_a_shipped_one_and_overrides_apply_last(tmp_path):
    f = tmp_path / "mine.toml"
    f.write_text('base = "thesis"\nname = "mine"\n[motion]\nmean_step_m = 0.002\n')
    scn = load_scenario(str(f), ["motion.mean_roll_deg=1.5"])
    thesis = load_scenario("thesis")
    assert scn["motion"]["mean_step_m"] == 0.002 and scn["motion"]["mean_roll_deg"] == 1.5
    assert scn["tube"] == thesis["tube"] and scn["name"] == "mine" and "base" not in scn
    f.write_text('base = "thesis"\n')  # no name of its own: its file's, not its base's
    assert load_scenario(str(f))["name"] == "mine" and "description" not in load_scenario(str(f))


@pytest.mark.parametrize("text, message", [('base = "mine"\n', "mine.toml: its base: unknown scenario 'mine'"),
                                           ('base = "x.toml"\n', "base must name another shipped scenario"),
                                           ("base = 3\n", "base must name another shipped scenario"),
                                           ('base = "nonesuch"\n', "mine.toml: its base: unknown scenario 'nonesuch'")])
def test_a_bad_base_is_refused_by_name(tmp_path, text, message):
    f = tmp_path / "mine.toml"
    f.write_text(text)
    with pytest.raises(ConfigError, match=message):
        load_scenario(str(f))


def test_a_scenario_that_is_its_own_base_is_refused(tmp_path, monkeypatch):
    import types

    import testbed.scenario as sc

    (tmp_path / "scenarios").mkdir()
    (tmp_path / "scenarios" / "loop.toml").write_text('base = "loop2"\n')
    (tmp_path / "scenarios" / "loop2.toml").write_text('base = "loop"\n')
    monkeypatch.setattr(sc, "resources", types.SimpleNamespace(files=lambda package: tmp_path))
    with pytest.raises(ConfigError, match="loop.toml: its base: .*loop2.toml: its base: .*loop.toml: base must "
                                          "name another shipped scenario, got 'loop2'"):
        load_scenario("loop")
    assert sc._loading == []  # nothing left behind for the next load


def test_a_tube_radius_out_of_range_names_its_keys():
    """``--set tube.radius_m=-1`` said "got -1.0 .. 0.015 m" (the start and end radii, unnamed); the keys and their
    values are named."""
    from testbed.scenario import build_world

    with pytest.raises(ConfigError, match=r"\[tube\] radius_m and radius_end_m .* got -1 and 0.015 m"):
        build_world(load_scenario("thesis", ["tube.radius_m=-1"]), 1, 5)
