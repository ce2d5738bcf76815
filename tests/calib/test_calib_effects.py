"""Hidden effects of the twin's truth: ``parse_effects``, ``TruthEffects`` and ``truth_model``."""

from __future__ import annotations

import pytest
from calib_helpers import small_phantom_mesh

import fem
from calib.model.effects import EFFECTS, EffectError, TruthEffects, parse_effects, truth_model

DEFAULT = TruthEffects(skin_thickness_mm=1.5, skin_ratio=8.0)  # a preset's default


def test_no_specs_give_the_preset_default():
    assert parse_effects([], default=DEFAULT) is DEFAULT


def test_none_gives_a_neutral_truth():
    eff = parse_effects(["none"], default=DEFAULT)
    assert eff == TruthEffects()
    assert eff.active() == []


@pytest.mark.parametrize(
    ("spec", "expected"),
    [
        ("skin", TruthEffects(skin_thickness_mm=1.5, skin_ratio=8.0)),
        ("skin=2.5:4", TruthEffects(skin_thickness_mm=2.5, skin_ratio=4.0)),
        ("skin=2", TruthEffects(skin_thickness_mm=2.0, skin_ratio=8.0)),
        ("sliding", TruthEffects(sliding=True)),
        ("sliding=yes", TruthEffects(sliding=True)),
        ("inclusions", TruthEffects(inclusion_ratio=5.0)),
        ("inclusions=0.5", TruthEffects(inclusion_ratio=0.5)),
        ("mooney", TruthEffects(c2_pa=210.0)),
        ("mooney=50", TruthEffects(c2_pa=50.0)),
        ("poisson", TruthEffects(nu=0.45)),
        ("poisson=0.3", TruthEffects(nu=0.3)),
        ("density", TruthEffects(density_kg_m3=1100.0)),
        ("density=950", TruthEffects(density_kg_m3=950.0)),
        (" Density = 950", TruthEffects(density_kg_m3=950.0)),
    ],
)
def test_each_effect_with_and_without_value(spec, expected):
    # Given effects replace the preset's default entirely (no skin unless asked for).
    assert parse_effects([spec], default=DEFAULT) == expected


def test_effects_combine():
    eff = parse_effects(["skin=1:10", "sliding", "density=1200"], default=DEFAULT)
    assert eff == TruthEffects(
        skin_thickness_mm=1.0, skin_ratio=10.0, sliding=True, density_kg_m3=1200.0
    )
    assert eff.active() == ["skin", "sliding", "density"]


def test_every_listed_effect_parses_without_value():
    for name in EFFECTS:
        eff = parse_effects([name], default=DEFAULT)
        assert eff.active() == ([] if name == "none" else [name])


@pytest.mark.parametrize(
    ("specs", "pattern"),
    [
        (["wrinkles"], r"unknown effect 'wrinkles'; choose from density, inclusions, mooney, none"),
        (["poisson=0.5"], r"effect 'poisson': value 0.5 outside the range \[0.3, 0.4999\]"),
        (["poisson=0.2"], r"effect 'poisson': value 0.2 outside the range"),
        (["skin=20:8"], r"effect 'skin': value 20.0 outside the range \[0.0, 10.0\] mm"),
        (["skin=1.5:0"], r"effect 'skin': value 0.0 outside the range \[0.1, 100.0\]"),
        (["inclusions=0"], r"effect 'inclusions': value 0.0 outside the range"),
        (["mooney=-1"], r"effect 'mooney': value -1.0 outside the range \[0.0, 10000.0\]"),
        (
            ["density=100"],
            r"effect 'density': value 100.0 outside the range \[500.0, 2000.0\] kg/m\^3",
        ),
        (["density=inf"], r"effect 'density': value inf outside the range"),
        (["poisson=nan"], r"effect 'poisson': value nan outside the range"),
        (["poisson=abc"], r"effect 'poisson': 'abc' is not a number"),
        (["skin=thick:8"], r"effect 'skin': 'thick' is not a number"),
        (["sliding=0"], r"effect 'sliding': value 0.0 outside the range \[10.0, 1000000.0\] Pa/mm"),
        (["sliding=stiff"], r"effect 'sliding': 'stiff' is not a number"),
        (["none", "skin"], r"'none' cannot be combined with other effects"),
        (["skin", "none"], r"'none' cannot be combined with other effects"),
    ],
)
def test_bad_effects(specs, pattern):
    with pytest.raises(EffectError, match=pattern):
        parse_effects(specs, default=DEFAULT)


def test_sliding_is_frictionless_or_on_springs_of_a_given_stiffness():
    free = parse_effects(["sliding"], default=DEFAULT)
    springs = parse_effects(["sliding=1000"], default=DEFAULT)
    assert free.values(420.0).support == "sliding"
    assert springs.values(420.0).support == "springs"
    assert springs.values(420.0).support_stiffness_pa_per_mm == 1000.0
    assert springs.active() == ["sliding"]
    assert TruthEffects().values(420.0).support == "clamped"


def test_effect_error_is_a_value_error():
    assert issubclass(EffectError, ValueError)


def test_none_takes_no_value():
    with pytest.raises(EffectError, match="none"):
        parse_effects(["none=3"], default=DEFAULT)


def test_active():
    assert TruthEffects().active() == []
    # A skin layer is an effect only with a thickness AND a stiffness different from the bulk.
    assert TruthEffects(skin_thickness_mm=1.5, skin_ratio=1.0).active() == []
    assert TruthEffects(skin_thickness_mm=0.0, skin_ratio=8.0).active() == []
    assert TruthEffects(skin_thickness_mm=1.5, skin_ratio=8.0).active() == ["skin"]
    assert TruthEffects(sliding=True).active() == ["sliding"]
    assert TruthEffects(inclusion_ratio=2.0).active() == ["inclusions"]
    assert TruthEffects(c2_pa=1.0).active() == ["mooney"]
    assert TruthEffects(nu=0.45).active() == ["poisson"]
    assert TruthEffects(density_kg_m3=1100.0).active() == ["density"]
    every = TruthEffects(1.5, 8.0, True, 3.0, 10.0, 0.45, 1100.0)
    assert every.active() == ["skin", "sliding", "inclusions", "mooney", "poisson", "density"]


@pytest.fixture(scope="module")
def meshes():
    return {"skin": small_phantom_mesh()[1], "plain": small_phantom_mesh(skin_thickness_mm=0)[1]}


def _kappa(c1, c2, nu):
    # Small strain: mu = 2 (c1 + c2), kappa = 2 mu (1 + nu) / (3 (1 - 2 nu)).
    mu = 2.0 * (c1 + c2)
    return 2.0 * mu * (1.0 + nu) / (3.0 * (1.0 - 2.0 * nu))


def test_truth_model_regions_and_materials(meshes):
    mesh = meshes["skin"]
    partial = {n for n in mesh.region_names if n.startswith("skin:")}
    assert partial  # 14 mm elements against a 3 mm band: most skin elements are partial
    assert set(mesh.region_names) == {"bulk", "inclusion", "skin"} | partial
    eff = TruthEffects(skin_thickness_mm=3.0, skin_ratio=8.0, inclusion_ratio=5.0,
                       c2_pa=100.0, nu=0.45, density_kg_m3=1100.0)  # fmt: skip
    model = truth_model(mesh, 420.0, eff)
    assert model.mesh is mesh
    assert set(model.materials) == set(mesh.region_names)
    expected = {"bulk": (420.0, 100.0), "inclusion": (2100.0, 500.0), "skin": (3360.0, 800.0)}
    for name in partial:  # volume (Voigt) mix: 1 + (8 - 1) f times the bulk's constants
        f = float(name.split(":")[1])
        expected[name] = (420.0 * (1 + 7 * f), 100.0 * (1 + 7 * f))
    for region, (c1, c2) in expected.items():
        law = model.materials[region]
        assert isinstance(law, fem.MooneyRivlin)
        # Products of exact decimal inputs: round-off only.
        assert law.c1_pa == pytest.approx(c1, rel=1e-12)
        assert law.c2_pa == pytest.approx(c2, rel=1e-12)
        assert law.volumetric.kappa_pa == pytest.approx(_kappa(c1, c2, 0.45), rel=1e-12)
    assert set(model.density_kg_m3.values()) == {1100.0}
    assert isinstance(model.support, fem.Clamped)


def test_truth_model_neutral_and_sliding(meshes):
    model = truth_model(meshes["plain"], 420.0, TruthEffects(sliding=True))
    assert set(model.materials) == {"bulk", "inclusion"}
    for law in model.materials.values():
        assert (law.c1_pa, law.c2_pa) == (420.0, 0.0)
        assert law.volumetric.kappa_pa == pytest.approx(_kappa(420.0, 0.0, 0.499), rel=1e-12)
    assert dict(model.density_kg_m3) == {"bulk": 1000.0, "inclusion": 1000.0}
    assert isinstance(model.support, fem.Sliding)


def test_truth_model_neutral_skin_is_the_bulk(meshes):
    # A tagged skin band with ratio 1 is the bulk material (no hidden effect).
    model = truth_model(meshes["skin"], 420.0, TruthEffects(skin_thickness_mm=3.0))
    assert all(law == model.materials["bulk"] for law in model.materials.values())
