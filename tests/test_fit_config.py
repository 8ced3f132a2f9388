"""A fit config read strictly (issue #33): YAML's loose types never turn into a wrong setting."""

from __future__ import annotations

import math

import pytest

from torch_diffavatar.errors import InputError
from torch_diffavatar.fit_config import CONFIG_DIR, FitConfig, load_config


def _load(tmp_path, text: str) -> FitConfig:
    path = tmp_path / "c.yaml"
    path.write_text(text)
    return load_config(path)


def test_numbers_that_yaml_reads_as_strings_parse(tmp_path):
    # YAML 1.1 (PyYAML) reads 1e-3 as the string "1e-3": it failed deep in the fit with a TypeError
    config = _load(tmp_path, "lr_cage: 1e-3\nweights: {boundary: 2e3}\niterations: 7\n")
    assert config.lr_cage == 0.001 and isinstance(config.lr_cage, float)
    assert config.weights.boundary == 2000.0
    assert config.iterations == 7


@pytest.mark.parametrize(
    "line, message",
    [
        ('cage: "no"', "cage must be true or false"),  # a non-empty string read as true before
        ('keep_best: "false"', "keep_best must be true or false"),
        ("tie_seams: 0", "tie_seams must be true or false"),
        ("iterations: 2.5", "iterations must be an integer"),
        ("iterations: true", "iterations must be an integer"),
        ("max_retries: -5", "max_retries must be an integer >= 0"),  # skipped every step before
        ("max_drape_jump: .nan", "max_drape_jump must be a finite number"),  # switched the guard off
        ("lr_cage: .inf", "lr_cage must be a finite number"),
        ("initial_bend_stiffness: .inf", "initial_bend_stiffness must be in \\[1e-9, 1e-2\\] N·m"),
        ("lr_cage: fast", "lr_cage must be a number"),
        ("weights: {boundary: true}", "weights.boundary must be a number"),
        ("weights: {boundary: .nan}", "LossWeights.boundary must be a finite number"),
        ("template: 3", "template must be a string"),
        ("boundary_gap_bin: -0.03", "boundary_gap_bin must be >= 0"),
        ("boundary_gap_bin: .inf", "boundary_gap_bin must be >= 0"),
        ("drape_velocity_scale: 1.5", "drape_velocity_scale must be in \\(0, 1\\]"),  # energy would grow
        ("drape_velocity_scale: 0", "drape_velocity_scale must be in \\(0, 1\\]"),
        ("drape_contact_bounce: -1", "drape_contact_bounce must be in \\[0, 1\\]"),
        ("animation_check_s: -0.5", "animation_check_s must be in \\[0, inf\\)"),
        ("opening_template_hold: both", "opening_template_hold must be one of \\('least', 'exact'\\)"),
        ("first_fit_bend_scales: [1, -3]\nfirst_race_iterations: 5", "first_fit_bend_scales must be"),
        ("first_fit_bend_scales: [1, 3]\nfirst_race_iterations: 0", "several bending stiffnesses need"),
        # every variable frozen: the whole set-up ran, then Adam failed with a traceback
        (
            "lr_cage: 0\nlr_phenotypes: 0\nlr_translation: 0\nlr_pose: 0\nlr_log_bend_stiffness: 0",
            "every learning rate .* is 0, so nothing would be fitted",
        ),
    ],
)
def test_values_of_the_wrong_type_or_range_are_refused(tmp_path, line, message):
    with pytest.raises(InputError, match=message):
        _load(tmp_path, line + "\n")


def test_infinity_switches_a_guard_off_and_nothing_else(tmp_path):
    config = _load(tmp_path, "max_loss_rise: .inf\nmax_drape_jump: .inf\n")
    assert math.isinf(config.max_loss_rise) and math.isinf(config.max_drape_jump)
    with pytest.raises(ValueError, match="robust_scale must be a finite number"):
        FitConfig(robust_scale=math.inf)


def test_a_null_where_a_length_or_nothing_is_allowed(tmp_path):
    assert _load(tmp_path, "arms_low_spacing: null\n").arms_low_spacing is None
    assert _load(tmp_path, "arms_low_spacing: '0.03'\n").arms_low_spacing == 0.03


def test_the_fit_drapes_with_its_own_damping():
    """`drape_velocity_scale` and `drape_contact_bounce` reach every warm-started drape of a fit, with
    either adjoint; the first (sew and) drape keeps the drape default."""
    from torch_diffavatar.fit_config import drape_config, first_drape_config
    from torch_diffavatar.sim.forward_drape import DrapeConfig

    config = FitConfig(drape_velocity_scale=0.9, drape_contact_bounce=0.0)
    for adjoint in ("equilibrium", "trajectory"):
        assert drape_config(config, adjoint=adjoint).drape_velocity_scale == 0.9
        assert drape_config(config, adjoint=adjoint).xpbd.contact_bounce == 0.0
    assert drape_config(FitConfig()).drape_velocity_scale == DrapeConfig().drape_velocity_scale
    assert first_drape_config(config).drape_velocity_scale == DrapeConfig().drape_velocity_scale
    assert first_drape_config(config).xpbd.contact_bounce == 1.0


def test_valley_contacts_reach_the_fit_drapes_and_the_first_one(tmp_path):
    """`drape_valley_contacts` (off by default) reaches every drape of a fit, the first one's drape too
    (not its sewing, whose band is wide)."""
    from torch_diffavatar.fit_config import drape_config, first_drape_config

    assert not drape_config(FitConfig()).xpbd.valley_contacts
    assert not first_drape_config(FitConfig()).xpbd.valley_contacts
    config = _load(tmp_path, "drape_valley_contacts: true\n")
    for adjoint in ("equilibrium", "trajectory"):
        assert drape_config(config, adjoint=adjoint).xpbd.valley_contacts
    first = first_drape_config(config)
    assert first.xpbd.valley_contacts and not first.sew_xpbd.valley_contacts
    assert first.xpbd.max_strain == drape_config(config).xpbd.max_strain  # the fit's strain limit kept


def test_the_floor_reaches_every_drape_of_a_fit(tmp_path):
    """`drape_floor` (on by default) reaches the fit's drapes, its first drape and that drape's sewing."""
    from torch_diffavatar.fit_config import drape_config, first_drape_config

    for adjoint in ("equilibrium", "trajectory"):
        assert drape_config(FitConfig(), adjoint=adjoint).floor
    assert first_drape_config(FitConfig()).floor
    config = _load(tmp_path, "drape_floor: false\n")
    assert not drape_config(config).floor and not first_drape_config(config).floor


@pytest.mark.parametrize("path", sorted(CONFIG_DIR.glob("*.yaml")), ids=lambda p: p.stem)
def test_the_openings_each_shipped_config_holds_are_openings_of_its_template(path):
    """A held name that no opening of the garment has is held nowhere, silently (the dress's armholes are
    its ``cuff_left`` and ``cuff_right``)."""
    from torch_diffavatar.pattern import load_template, mesh_pattern

    config = load_config(path)
    loops = {loop.name for loop in mesh_pattern(load_template(config.template), spacing=0.05).boundary_loops}
    assert set(config.opening_template_names) <= loops, (config.opening_template_names, loops)
    # held at the template's length where that was measured to help (docs/BENCHMARKS.md, "Openings held at the
    # template's"): the dress's neck and armholes, the trousers' waist; the tops' necks no shorter
    exact = config.template in ("dress", "pants")
    assert config.opening_template_hold == ("exact" if exact else "least"), config.opening_template_hold


@pytest.mark.parametrize("path", sorted(CONFIG_DIR.glob("*.yaml")), ids=lambda p: p.stem)
def test_the_dress_races_its_bending_stiffness_and_membrane_and_the_others_start_at_one(path):
    """The dress config starts its fit from two (membrane, bending stiffness) pairs and keeps the lower loss
    after a short race, the long sleeve sews each of its fold states at two membranes (docs/BENCHMARKS.md,
    "A race of bending stiffnesses", "A race of membranes"); no other config pays for one. The soft
    membrane lies inside the factor's bound."""
    config = load_config(path)
    if config.template == "dress":
        # two candidates: the nominal membrane at 3x k_b, one 50x softer at 1x
        assert config.first_race_pairs and 0 < config.first_race_iterations < config.iterations
        assert config.first_stretch_scales == (1, 0.02) and config.first_fit_bend_scales == (3, 1)
        assert config.stretch_bound > 1 / 0.02
        assert config.lr_log_stretch == 0  # the race picks the membrane; the fit does not move it
    elif config.template == "longsleeve":  # each sewing also at the soft membrane: six whole-fit candidates
        assert config.first_stretch_scales == (1, 0.02) and not config.first_race_pairs
        assert config.first_race_iterations == config.iterations and config.stretch_bound > 1 / 0.02
        assert config.first_fit_bend_scales == (1.0,) and config.lr_log_stretch == 0
    else:
        assert config.first_fit_bend_scales == (1.0,) and config.first_stretch_scales == (1.0,)


@pytest.mark.parametrize("path", sorted(CONFIG_DIR.glob("*.yaml")), ids=lambda p: p.stem)
def test_the_waist_held_garments_fit_their_waists_height(path):
    """Skirts and trousers are worn where the body and the scan put them: a fit that holds the waist at the
    template's height grows the legs down to a pair worn low (Newton's trousers of seed 0, 4.1 cm low: 4.4 cm
    long; docs/BENCHMARKS.md, "Trousers worn low: the waist's height fitted")."""
    config = load_config(path)
    assert (config.lr_waist_shift > 0) == (config.template in ("skirt", "pants")), config.lr_waist_shift


@pytest.mark.parametrize("path", sorted(CONFIG_DIR.glob("*.yaml")), ids=lambda p: p.stem)
def test_a_skirt_starts_stiffer_than_the_other_garments(path):
    """A skirt that races no bending stiffness starts it at 3x the others' 5e-6 N*m: from 5e-6 its k_b fell to
    0.03x the truth's and the fit widened the hem 13.7 cm to reach the scan's flare, from the true pattern
    (docs/BENCHMARKS.md, "From the true pattern on Newton's scans at rest")."""
    config = load_config(path)
    start = 1.5e-5 if config.template == "skirt" else 5.0e-6
    assert config.initial_bend_stiffness == pytest.approx(start), config.initial_bend_stiffness
