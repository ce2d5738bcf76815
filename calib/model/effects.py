"""Physical effects that the digital twin can hide in its truth model.

Each effect has a neutral value that switches it off. The truth model is built
from the model description of :mod:`fem.model` alone: an effect is a region
material, a law, a density or a support — never a change to the solver.
"""

from __future__ import annotations

from dataclasses import dataclass

import fem
from fem.meshing import skin_fraction

__all__ = ["EFFECTS", "EffectError", "TruthEffects", "parse_effects", "truth_model"]


class EffectError(ValueError):
    """An unknown effect or an out-of-range effect value."""


@dataclass(frozen=True)
class TruthEffects:
    """Effect values of a truth model (the defaults are neutral: no effect).

    Attributes
    ----------
    skin_thickness_mm, skin_ratio : float
        Skin layer thickness and its stiffness relative to the bulk.
    sliding : bool
        Back plate free to slide in its plane (held at its rim).
    inclusion_ratio : float
        Stiffness of the inclusions relative to the bulk.
    c2_pa : float
        Mooney-Rivlin c2 of the bulk.
    nu : float
        Poisson's ratio of every region.
    density_kg_m3 : float
        True density (the session declares 1000 kg/m^3).
    """

    skin_thickness_mm: float = 0.0
    skin_ratio: float = 1.0
    sliding: bool = False
    inclusion_ratio: float = 1.0
    c2_pa: float = 0.0
    nu: float = 0.499
    density_kg_m3: float = 1000.0

    def active(self) -> list[str]:
        """Names of the effects that differ from neutral."""
        n = TruthEffects()
        out = []
        if self.skin_thickness_mm > 0 and self.skin_ratio != 1.0:
            out.append("skin")
        checks = (("sliding", self.sliding != n.sliding),
                  ("inclusions", self.inclusion_ratio != n.inclusion_ratio),
                  ("mooney", self.c2_pa != n.c2_pa), ("poisson", self.nu != n.nu),
                  ("density", self.density_kg_m3 != n.density_kg_m3))  # fmt: skip
        return out + [name for name, on in checks if on]


# name -> (default value when given without one, parser, valid range text)
EFFECTS = {
    "none": None,
    "skin": "1.5:8",
    "sliding": None,
    "inclusions": "5",
    "mooney": "210",
    "poisson": "0.45",
    "density": "1100",
}


def _number(text: str, name: str, lo: float, hi: float) -> float:
    try:
        v = float(text)
    except ValueError:
        raise EffectError(f"effect {name!r}: {text!r} is not a number") from None
    if not lo <= v <= hi:
        raise EffectError(f"effect {name!r}: value {v} outside the range [{lo}, {hi}]")
    return v


def _apply(eff: dict, name: str, value: str | None) -> None:
    if name == "sliding":
        if value not in (None, "1", "true", "yes"):
            raise EffectError("effect 'sliding' takes no value")
        eff["sliding"] = True
        return
    value = value or EFFECTS[name]
    if name == "skin":
        t, _, r = value.partition(":")
        eff["skin_thickness_mm"] = _number(t, name, 0.0, 10.0)
        eff["skin_ratio"] = _number(r or "8", name, 0.1, 100.0)
    elif name == "inclusions":
        eff["inclusion_ratio"] = _number(value, name, 0.1, 100.0)
    elif name == "mooney":
        eff["c2_pa"] = _number(value, name, 0.0, 1e4)
    elif name == "poisson":
        eff["nu"] = _number(value, name, 0.3, 0.4999)
    elif name == "density":
        eff["density_kg_m3"] = _number(value, name, 500.0, 2000.0)


def parse_effects(specs: list[str], *, default: TruthEffects) -> TruthEffects:
    """Parse ``NAME[=VALUE]`` strings (``skin=1.5:8`` is thickness mm : stiffness ratio).

    With no specs the preset's ``default`` is returned; ``none`` gives a neutral truth.
    """
    if not specs:
        return default
    eff: dict = {}
    seen: set[str] = set()
    for spec in specs:
        name, sep, value = spec.partition("=")
        name = name.strip().lower()
        if name not in EFFECTS:
            raise EffectError(f"unknown effect {name!r}; choose from {sorted(EFFECTS)}")
        if name in seen:
            raise EffectError(f"effect {name!r} given twice")
        seen.add(name)
        if sep and not value.strip():
            raise EffectError(f"effect {name!r}: empty value after '='")
        if name == "none":
            if sep:
                raise EffectError("effect 'none' takes no value")
            if len(specs) > 1:
                raise EffectError("effect 'none' cannot be combined with other effects")
            return TruthEffects()
        _apply(eff, name, value if sep else None)
    return TruthEffects(**eff)


def _law(c1: float, c2: float, nu: float) -> fem.MooneyRivlin:
    return fem.MooneyRivlin.from_poisson(c1, c2, nu)


def truth_model(mesh: fem.TetMesh, c1_pa: float, effects: TruthEffects) -> fem.Model:
    """The truth model of a phantom mesh (regions bulk, inclusion, skin) with effects."""
    e = effects
    materials = {"bulk": _law(c1_pa, e.c2_pa, e.nu)}
    if "inclusion" in mesh.region_names:
        materials["inclusion"] = _law(c1_pa * e.inclusion_ratio, e.c2_pa * e.inclusion_ratio, e.nu)
    for name in mesh.region_names:
        frac = skin_fraction(name)
        if frac is not None:  # volume mix of skin and bulk (Voigt): exact as h -> 0
            ratio = 1.0 + (e.skin_ratio - 1.0) * frac
            materials[name] = _law(c1_pa * ratio, e.c2_pa * ratio, e.nu)
    density = {name: e.density_kg_m3 for name in materials}
    support = fem.Sliding() if e.sliding else fem.Clamped()
    unknown = set(mesh.region_names) - set(materials)
    if unknown:
        raise ValueError(f"truth model has no material for region(s) {sorted(unknown)}")
    return fem.Model(mesh, materials, density, support)
