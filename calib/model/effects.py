"""The effect library: physical effects the model may miss, shared by the twin and the diagnosis.

Each effect is a parameter with a neutral value (the effect switched off), a physical
range and an FE implementation in the model description of :mod:`fem.model` — a
region material, a law, a density, a support or the load — never a change to the
solver. Two users:

- the digital twin hides effects in its truth (``phantom-calib synth --effect``,
  :class:`TruthEffects`, :func:`parse_effects`, :func:`truth_model`);
- the missing-effect diagnosis (``phantom-calib diagnose``, :mod:`calib.discrepancy`)
  adds them to the calibration model (:class:`EffectValues`, :func:`tag_effect_regions`,
  :func:`effect_model`) and fits their parameters (:data:`LIBRARY`).

Both build their materials with the same function (:func:`region_law`): an element
carries the volume fractions of skin band and inclusion inside it (64 sub-tetrahedra
sampled) and mixes the laws by them (the twin's ``skin:f`` regions; the model mesh's
``skin:f``, ``inclusion:f`` and ``mix:fs:fi`` regions). The skin band mixes by volume
(Voigt): a thin layer along the surface is stretched with its neighbours, so a layer's
stiffness times volume does not depend on the mesh. An inclusion's part of an element
mixes by the Hashin-Shtrikman bound with the bulk as the connected phase
(:func:`inclusion_mix`): a stiff sphere in a soft element stiffens it far less than its
volume share of the stiffness (an element 30 % inside a ×5 inclusion: ×1.57, not ×2.2),
and with the volume mix a refit on a coarse mesh found the ratio − 1 at 2.0–2.3 against
a true 4.

The library's effects (parameters of the diagnosis; neutral value; physical range):

============ ===================================== ============ =======================
effect       parameter                             neutral      range
============ ===================================== ============ =======================
skin         skin/bulk stiffness ratio - 1 (band   0            [-0.9, 99]
             of ``SKIN_THICKNESS_MM`` at the outer
             surface, not the back plate)
sliding      back-plate support: clamped, tangential springs (``fem.Sliding`` with
             ``tangent_stiffness_pa_per_mm``, rim held) or frictionless; the
             diagnosis screens it with a stiff-spring probe (one FE solve per scan) and
             refits ``ln k`` (``calib.discrepancy.refit.sliding_ln_k_bounds``)
inclusions   inclusion/bulk stiffness ratio - 1    0            [-0.9, 99]
mooney       c2 / c1 (Mooney-Rivlin, strain        0            [0, 4]
             stiffening of the I2 term)
poisson      nu                                    model's nu   [0.3, 0.4999]
density      ln of density / declared density      0            [ln 0.5, ln 2]
             (not identifiable: at fixed nu the solution depends on rho g / c1 only)
gravity      2 angles of the gravity direction     0            +-5 degrees, per scan
             error per scan (rad)
registration rigid offset per scan: 3              0            +-3 mm (or twice the
             translations (mm), 3 rotations (rad)              scan's registration
                                                               tolerance), +-2 degrees
============ ===================================== ============ =======================

The skin and inclusion parameters are the stiffness ratio less one, not its logarithm:
an element's stiffness is linear in it (an element only partly inside an inclusion:
concave, the Hashin-Shtrikman mix), so the residual is nearly linear too and a
Gauss-Newton step from neutral lands near the answer (in ln ratio a step from 1 to 8
overshoots by the exponential's curvature).

References
----------
Voigt, W. (1889). Ueber die Beziehung zwischen den beiden Elasticitätsconstanten
isotroper Körper. *Ann. Phys.* 274, 573-587 (the volume mix of the skin band).
Hashin, Z. & Shtrikman, S. (1963). A variational approach to the theory of the elastic
behaviour of multiphase materials. *J. Mech. Phys. Solids* 11, 127-140 (the inclusion's
mix: the shear-modulus bound with the soft phase connected).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from typing import Literal

import numpy as np

import fem
from fem.mesh import REGION_IDS
from fem.meshing import skin_fraction
from fem.units import DEFAULT_DENSITY_KG_M3

from ..stats.scores import ALTERNATIVES

__all__ = [
    "ADMISSIBLE",
    "EFFECTS",
    "LIBRARY",
    "SKIN_THICKNESS_MM",
    "Effect",
    "EffectError",
    "EffectValues",
    "TruthEffects",
    "effect_model",
    "effect_support",
    "inclusion_mix",
    "parse_effects",
    "region_fractions",
    "region_law",
    "tag_effect_regions",
    "truth_model",
]

#: Thickness of the skin band of the diagnosis' model (mm): the dissertation's suspected
#: 1.5 mm layer. For a layer thin against the body, ``(ratio - 1) * thickness`` is what
#: the surface shape sees (the layer's added membrane stiffness), so the fitted ratio
#: at this thickness stands for that product.
SKIN_THICKNESS_MM = 1.5


#: The parameter values the model admits (:class:`EffectValues`' checks), per global
#: effect whose parameter is bounded: a stiffness ratio above 0, c2 >= 0, nu in (0,
#: 0.5). Wider than :attr:`Effect.bounds` (the search range) and certain: a truth lies
#: inside, so an interval cut to it keeps its coverage. ``sliding``'s ln k is unbounded.
ADMISSIBLE: dict[str, tuple[float, float]] = {
    "skin": (-1.0, math.inf),
    "inclusions": (-1.0, math.inf),
    "mooney": (0.0, math.inf),
    "poisson": (0.0, 0.5),
}


class EffectError(ValueError):
    """An unknown effect or an out-of-range effect value."""


# ------------------------------------------------------------------------ values


@dataclass(frozen=True)
class EffectValues:
    """Values of every FE-implemented effect of a model (the defaults are neutral).

    Attributes
    ----------
    skin_ratio : float
        Stiffness of the skin band relative to the bulk (regions ``skin``, ``skin:f``).
    inclusion_ratio : float
        Stiffness of the inclusions relative to the bulk (``inclusion``, ``inclusion:f``).
    c2_ratio : float
        Mooney-Rivlin ``c2 / c1`` of every region (0: neo-Hookean).
    nu : float
        Poisson's ratio of every region.
    density_kg_m3 : float
    support_stiffness_pa_per_mm : float
        Tangential springs of the back plate per area: ``inf`` clamped, ``0``
        frictionless (the plate's rim held in its plane), in between springs.
    """

    skin_ratio: float = 1.0
    inclusion_ratio: float = 1.0
    c2_ratio: float = 0.0
    nu: float = 0.499
    density_kg_m3: float = DEFAULT_DENSITY_KG_M3
    support_stiffness_pa_per_mm: float = math.inf

    def __post_init__(self) -> None:
        for name in ("skin_ratio", "inclusion_ratio"):
            v = getattr(self, name)
            if not (v > 0 and np.isfinite(v)):
                raise EffectError(f"{name} must be positive and finite, got {v}")
        if not (self.c2_ratio >= 0 and np.isfinite(self.c2_ratio)):
            raise EffectError(f"c2_ratio must be >= 0 and finite, got {self.c2_ratio}")
        if not 0.0 < self.nu < 0.5:
            raise EffectError(f"nu must lie in (0, 0.5), got {self.nu}")
        if not (self.density_kg_m3 > 0 and np.isfinite(self.density_kg_m3)):
            raise EffectError(f"density must be positive and finite, got {self.density_kg_m3}")
        if not self.support_stiffness_pa_per_mm >= 0:
            raise EffectError(
                f"support stiffness must be >= 0 (inf: clamped), got "
                f"{self.support_stiffness_pa_per_mm}"
            )

    @property
    def support(self) -> str:
        """``"clamped"``, ``"sliding"`` (frictionless) or ``"springs"``."""
        k = self.support_stiffness_pa_per_mm
        return "clamped" if math.isinf(k) else ("sliding" if k == 0 else "springs")

    def as_json(self) -> dict:
        """Plain JSON (``inf`` as the string ``"inf"``)."""
        k = self.support_stiffness_pa_per_mm
        return {
            "skin_ratio": self.skin_ratio,
            "inclusion_ratio": self.inclusion_ratio,
            "c2_ratio": self.c2_ratio,
            "nu": self.nu,
            "density_kg_m3": self.density_kg_m3,
            "support_stiffness_pa_per_mm": "inf" if math.isinf(k) else k,
            "support": self.support,
        }

    @classmethod
    def from_json(cls, doc: dict) -> EffectValues:
        """Inverse of :meth:`as_json`."""
        k = doc.get("support_stiffness_pa_per_mm", "inf")
        return cls(
            skin_ratio=float(doc.get("skin_ratio", 1.0)),
            inclusion_ratio=float(doc.get("inclusion_ratio", 1.0)),
            c2_ratio=float(doc.get("c2_ratio", 0.0)),
            nu=float(doc.get("nu", 0.499)),
            density_kg_m3=float(doc.get("density_kg_m3", DEFAULT_DENSITY_KG_M3)),
            support_stiffness_pa_per_mm=math.inf if k == "inf" else float(k),
        )


def effect_support(values: EffectValues, node_set: str = "back"):
    """The fem support of the back plate for these values."""
    k = values.support_stiffness_pa_per_mm
    if math.isinf(k):
        return fem.Clamped(node_set)
    return fem.Sliding(node_set, hold="rim", tangent_stiffness_pa_per_mm=float(k))


# ---------------------------------------------------------------------- regions

_SKIN_SUBTETS_TAG = 300  # tags 301..363: elements partly in the skin band (k / 64)
_PARTIAL_INCLUSION_TAG = 400  # 401..463: partly in an inclusion
_MIX_TAG = 1000
_SUBTET_LEVELS = 2  # two red refinements: volume fractions in steps of 1/64
_SUBTETS = 8**_SUBTET_LEVELS


def region_fractions(name: str) -> tuple[float, float]:
    """Volume fractions ``(skin, inclusion)`` of a region from its name.

    ``bulk`` (0, 0); ``skin`` (1, 0); ``skin:f`` (f, 0); ``inclusion`` (0, 1);
    ``inclusion:f`` (0, f); ``mix:fs:fi`` (fs, fi).

    Raises
    ------
    EffectError
        A name of none of these forms.
    """
    if name == "bulk":
        return 0.0, 0.0
    if name == "inclusion":
        return 0.0, 1.0
    if name.startswith("inclusion:"):
        return 0.0, float(name.split(":", 1)[1])
    if name.startswith("mix:"):
        _, fs, fi = name.split(":")
        return float(fs), float(fi)
    fs = skin_fraction(name)
    if fs is None:
        raise EffectError(f"region {name!r} has no effect fractions (expected bulk, skin[:f], "
                          "inclusion[:f] or mix:fs:fi)")  # fmt: skip
    return fs, 0.0


def _subtet_points(mesh: fem.TetMesh) -> np.ndarray:
    """Centroids of the 64 equal sub-tetrahedra of every element, shape (m, 64, 3)."""
    from fem.meshing import subtet_centroids  # the twin's sampling of a skin band

    bary = subtet_centroids(_SUBTET_LEVELS)
    return np.einsum("pk,ekj->epj", bary, mesh.nodes_mm[mesh.tets])


def _outer_distance_mm(mesh: fem.TetMesh, points: np.ndarray) -> np.ndarray:
    """Distance (mm) of points to the outer surface (the boundary without the back face)."""
    import open3d as o3d

    faces = fem.boundary_faces(mesh.tets)
    back = np.zeros(mesh.n_nodes, bool)
    back[mesh.node_set("back")] = True
    outer = faces[~back[faces].all(axis=1)]
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(
        o3d.core.Tensor(mesh.nodes_mm.astype(np.float32)), o3d.core.Tensor(outer.astype(np.uint32))
    )
    d = scene.compute_distance(o3d.core.Tensor(points.reshape(-1, 3).astype(np.float32)))
    return d.numpy().astype(float).reshape(points.shape[:-1])


def tag_effect_regions(
    mesh: fem.TetMesh,
    *,
    skin_thickness_mm: float = SKIN_THICKNESS_MM,
    inclusions: Sequence[tuple[Sequence[float], float]] = (),
) -> fem.TetMesh:
    """Tag a model mesh by the volume fractions of skin band and inclusions in its elements.

    Each element's 64 sub-tetrahedron centroids are classified: inside an inclusion
    sphere (it takes precedence), else within ``skin_thickness_mm`` of the outer surface
    (the boundary without the ``back`` node set's face), else bulk. Regions: ``bulk``,
    ``skin``, ``skin:f``, ``inclusion``, ``inclusion:f``, ``mix:fs:fi`` (fractions in
    steps of 1/64). Usable on any mesh with a ``back`` node set (no region of the mesh
    is read).

    Parameters
    ----------
    mesh : TetMesh
        Nodes in mm; node set ``back``.
    skin_thickness_mm : float
        Band thickness (0: no skin regions).
    inclusions : sequence of (centre_mm, diameter_mm)
        Spheres in the mesh's frame (e.g. the inclusions ingest detected in the
        reference scan).

    Returns
    -------
    TetMesh
        The same mesh with the region tags above.
    """
    if skin_thickness_mm < 0:
        raise EffectError(f"skin thickness must be >= 0, got {skin_thickness_mm}")
    pts = _subtet_points(mesh)
    inside = np.zeros(pts.shape[:2], bool)
    for centre, diameter in inclusions:
        if not diameter > 0:
            raise EffectError(f"inclusion diameter must be positive, got {diameter}")
        c = np.asarray(centre, float).reshape(3)
        inside |= np.linalg.norm(pts - c, axis=2) < 0.5 * float(diameter)
    band = np.zeros_like(inside)
    if skin_thickness_mm > 0:
        band = (_outer_distance_mm(mesh, pts) < skin_thickness_mm) & ~inside
    ks, ki = band.sum(axis=1), inside.sum(axis=1)
    region = np.full(mesh.n_tets, REGION_IDS["bulk"], dtype=np.int64)
    names = {"bulk": REGION_IDS["bulk"]}
    for a, b in {(int(x), int(y)) for x, y in zip(ks, ki, strict=True)} - {(0, 0)}:
        sel = (ks == a) & (ki == b)
        fs, fi = a / _SUBTETS, b / _SUBTETS
        if b == 0:
            name = "skin" if a == _SUBTETS else f"skin:{fs:.6g}"
            tag = REGION_IDS["skin"] if a == _SUBTETS else _SKIN_SUBTETS_TAG + a
        elif a == 0:
            name = "inclusion" if b == _SUBTETS else f"inclusion:{fi:.6g}"
            tag = REGION_IDS["inclusion"] if b == _SUBTETS else _PARTIAL_INCLUSION_TAG + b
        else:
            name, tag = f"mix:{fs:.6g}:{fi:.6g}", _MIX_TAG + (_SUBTETS + 1) * a + b
        region[sel] = tag
        names[name] = tag
    if not np.any(region == REGION_IDS["bulk"]):
        names.pop("bulk")
    return mesh.with_regions(region, names)


def inclusion_mix(fraction: float, ratio_minus_one: float) -> float:
    """Stiffening of an element a ``fraction`` of whose volume is inclusion, less one.

    The Hashin-Shtrikman bound of the shear modulus with the bulk as the connected
    phase, both incompressible (the bulk's bulk modulus taken to infinity):
    ``mu / mu_bulk - 1 = f d / (1 + 2 (1 - f) d / 5)``, ``d`` the inclusion's ratio
    less one. It is the Mori-Tanaka estimate for spheres, Eshelby's dilute sphere
    ``f 5 d / (5 + 2 d)`` as ``f -> 0``, ``d`` at ``f = 1`` and 0 at ``d = 0``; its slope
    in ``d`` at ``d = 0`` is ``f``, the volume mix's, so the screen's fields (taken at
    neutral) do not depend on the mix.

    Parameters
    ----------
    fraction : float
        Volume fraction of inclusion in the element, in [0, 1].
    ratio_minus_one : float
        Inclusion/bulk stiffness ratio less one, > -2.5 (the library's range: >= -0.9).
    """
    d = ratio_minus_one
    return fraction * d / (1.0 + 0.4 * (1.0 - fraction) * d)  # HS bound, K_bulk -> inf


def region_law(name: str, c1_pa: float, values: EffectValues) -> fem.MooneyRivlin:
    """The law of a region: bulk, skin band by volume, inclusion by Hashin-Shtrikman.

    ``ratio = 1 + (skin_ratio - 1) f_skin + inclusion_mix(f_inclusion, inclusion_ratio -
    1)`` (:func:`inclusion_mix`); ``c1 = ratio c1_pa``, ``c2 = ratio c2_ratio c1_pa``,
    Poisson's ratio ``values.nu``.
    """
    fs, fi = region_fractions(name)
    ratio = 1.0 + (values.skin_ratio - 1.0) * fs + inclusion_mix(fi, values.inclusion_ratio - 1.0)
    c1 = c1_pa * ratio
    return fem.MooneyRivlin.from_poisson(c1, c1_pa * values.c2_ratio * ratio, values.nu)


def effect_model(mesh: fem.TetMesh, c1_pa: float, values: EffectValues) -> fem.Model:
    """The FE model of a region-tagged mesh with effects (materials, density, support).

    Parameters
    ----------
    mesh : TetMesh
        Regions named as :func:`region_fractions` reads them; node set ``back``.
    c1_pa : float
        The bulk's c1.
    values : EffectValues

    Raises
    ------
    EffectError
        A region whose name carries no effect fractions.
    """
    materials = {name: region_law(name, c1_pa, values) for name in mesh.region_names}
    density = {name: values.density_kg_m3 for name in materials}
    return fem.Model(mesh, materials, density, effect_support(values))


# ---------------------------------------------------------------------- library


@dataclass(frozen=True)
class Effect:
    """One effect of the library: a parameter with a neutral value and a physical range.

    Attributes
    ----------
    name : str
    description : str
    kind : {"material", "support", "scaling", "nuisance"}
        ``material``: a region law (direct sensitivity); ``support``: the back plate
        (finite-difference FE solves); ``scaling``: a parameter the solution depends on
        only through ``rho g / c1`` (density: not identifiable); ``nuisance``: per-scan
        load or registration errors (no material change).
    parameter : str
        Name of the parameter.
    unit : str
    neutral : float
        The value that switches the effect off (for ``poisson``: the model's nu).
    bounds : tuple of float
        Physical range of the parameter.
    preset : float
        The twin's default amplitude (``--effect NAME``) in parameter units.
    per_scan : int
        Parameters per scan (nuisance effects); 0 for one global parameter.
    identifiable : bool
        False where the surface data cannot separate it from c1 in principle.
    implementation : str
        Where the effect lives in the FE model.
    direction : {-1, 0, 1}
        The sign a physical departure from neutral can take in the screened column: +1
        where neutral is the lower end of the range (mooney's c2 >= 0; the sliding
        probe's amplitude: a plate is never held tighter than clamped), -1 where it is
        the upper end (poisson: the model is nearly incompressible, 0.499 against
        0.4999), 0 both. The screening tests one-sided effects one-sided
        (:func:`calib.stats.screen_effects`).
    """

    name: str
    description: str
    kind: Literal["material", "support", "scaling", "nuisance"]
    parameter: str
    unit: str
    neutral: float
    bounds: tuple[float, float]
    preset: float
    per_scan: int = 0
    identifiable: bool = True
    implementation: str = ""
    direction: Literal[-1, 0, 1] = 0

    def set(self, values: EffectValues, p: float) -> EffectValues:
        """``values`` with this effect's parameter at ``p`` (global effects only)."""
        setter = _SETTERS.get(self.name)
        if setter is None:
            raise EffectError(f"effect {self.name!r} is not a model value (it is {self.kind})")
        return setter(values, float(p))

    def get(self, values: EffectValues) -> float:
        """The effect's parameter in ``values`` (global effects only)."""
        getter = _GETTERS.get(self.name)
        if getter is None:
            raise EffectError(f"effect {self.name!r} is not a model value (it is {self.kind})")
        return float(getter(values))

    def as_json(self) -> dict:
        """The library entry as plain JSON (for ``diagnosis.json``; infinities as strings)."""

        def num(v: float):
            return v if math.isfinite(v) else ("inf" if v > 0 else "-inf")

        return {
            "name": self.name,
            "description": self.description,
            "kind": self.kind,
            "parameter": self.parameter,
            "unit": self.unit,
            "neutral": num(self.neutral),
            "bounds": [num(b) for b in self.bounds],
            "preset": num(self.preset),
            "per_scan": self.per_scan,
            "identifiable": self.identifiable,
            "implementation": self.implementation,
            "alternative": ALTERNATIVES[self.direction],
        }


_SETTERS: dict[str, Callable[[EffectValues, float], EffectValues]] = {
    "skin": lambda v, p: replace(v, skin_ratio=1.0 + p),
    "inclusions": lambda v, p: replace(v, inclusion_ratio=1.0 + p),
    "mooney": lambda v, p: replace(v, c2_ratio=max(p, 0.0)),
    "poisson": lambda v, p: replace(v, nu=p),
    "density": lambda v, p: replace(v, density_kg_m3=DEFAULT_DENSITY_KG_M3 * math.exp(p)),
    "sliding": lambda v, p: replace(v, support_stiffness_pa_per_mm=math.exp(p)),
}
_GETTERS: dict[str, Callable[[EffectValues], float]] = {
    "skin": lambda v: v.skin_ratio - 1.0,
    "inclusions": lambda v: v.inclusion_ratio - 1.0,
    "mooney": lambda v: v.c2_ratio,
    "poisson": lambda v: v.nu,
    "density": lambda v: math.log(v.density_kg_m3 / DEFAULT_DENSITY_KG_M3),
    "sliding": lambda v: (
        math.log(v.support_stiffness_pa_per_mm) if v.support_stiffness_pa_per_mm > 0 else -math.inf
    ),
}

LIBRARY: dict[str, Effect] = {
    e.name: e
    for e in (
        Effect(
            "skin",
            f"stiffer outer layer ({SKIN_THICKNESS_MM} mm band at the outer surface)",
            "material",
            "excess_ratio",
            "skin c1 / bulk c1 - 1",
            0.0,
            (-0.9, 99.0),
            7.0,
            implementation="regions skin, skin:f, mix: volume mix of the laws",
        ),
        Effect(
            "sliding",
            "back plate sliding (clamped -> tangential springs -> frictionless)",
            "support",
            "ln_k",
            "ln(Pa/mm)",
            math.inf,
            (-math.inf, math.inf),
            -math.inf,
            implementation="fem.Sliding(hold='rim', tangent_stiffness_pa_per_mm=k)",
            direction=1,
        ),
        Effect(
            "inclusions",
            "inclusion stiffness (the inclusions ingest detected)",
            "material",
            "excess_ratio",
            "inclusion c1 / bulk c1 - 1",
            0.0,
            (-0.9, 99.0),
            4.0,
            implementation="regions inclusion, inclusion:f, mix: Hashin-Shtrikman mix",
        ),
        Effect(
            "mooney",
            "strain stiffening (Mooney-Rivlin c2)",
            "material",
            "c2_ratio",
            "c2 / c1",
            0.0,
            (0.0, 4.0),
            0.5,
            implementation="fem.MooneyRivlin(c1, c2) in every region",
            direction=1,
        ),
        Effect(
            "poisson",
            "compressibility (Poisson's ratio)",
            "material",
            "nu",
            "1",
            0.499,
            (0.3, 0.4999),
            0.45,
            implementation="bulk modulus of every region from nu",
            direction=-1,
        ),
        Effect(
            "density",
            "density (declared in session.toml)",
            "scaling",
            "ln_density_ratio",
            "ln(rho / rho_declared)",
            0.0,
            (math.log(0.5), math.log(2.0)),
            math.log(1.1),
            identifiable=False,
            implementation="density of every region; at fixed nu the solution depends on "
            "rho g / c1 only, so it is c1's own signature",
        ),
        Effect(
            "gravity",
            "gravity-direction error per scan",
            "nuisance",
            "angle",
            "rad",
            0.0,
            (-math.radians(5.0), math.radians(5.0)),
            0.0,
            per_scan=2,
            implementation="the load's direction, two rotations normal to it",
        ),
        Effect(
            "registration",
            "rigid registration offset per scan",
            "nuisance",
            "offset",
            "mm, rad",
            0.0,
            (-3.0, 3.0),
            0.0,
            per_scan=6,
            implementation="the measured points moved by dt + dw x (p - centre)",
        ),
    )  # fmt: skip
}


# ---------------------------------------------------------------------- the twin


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
    sliding_stiffness_pa_per_mm : float
        With ``sliding``, the tangential springs holding the plate (Pa/mm); 0: frictionless.
    """

    skin_thickness_mm: float = 0.0
    skin_ratio: float = 1.0
    sliding: bool = False
    inclusion_ratio: float = 1.0
    c2_pa: float = 0.0
    nu: float = 0.499
    density_kg_m3: float = DEFAULT_DENSITY_KG_M3
    sliding_stiffness_pa_per_mm: float = 0.0

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

    def values(self, c1_pa: float) -> EffectValues:
        """The library's :class:`EffectValues` of this truth at a bulk ``c1_pa``."""
        return EffectValues(
            skin_ratio=self.skin_ratio,
            inclusion_ratio=self.inclusion_ratio,
            c2_ratio=self.c2_pa / c1_pa,
            nu=self.nu,
            density_kg_m3=self.density_kg_m3,
            support_stiffness_pa_per_mm=self.sliding_stiffness_pa_per_mm
            if self.sliding
            else math.inf,
        )


# name -> default value when given without one (None: takes no value)
EFFECTS = {
    "none": None,
    "skin": f"{SKIN_THICKNESS_MM}:8",
    "sliding": None,
    "inclusions": "5",
    "mooney": "210",
    "poisson": "0.45",
    "density": "1100",
}

# the twin's values in their own units: name -> (lo, hi, unit said in a range error) of
# each number it takes
_TWIN_RANGES = {
    "skin": ((0.0, 10.0, " mm"), (0.1, 100.0, "")),  # thickness, stiffness ratio
    "inclusions": ((0.1, 100.0, ""),),
    "mooney": ((0.0, 1e4, " Pa"),),  # c2
    "poisson": ((*LIBRARY["poisson"].bounds, ""),),
    "density": ((500.0, 2000.0, " kg/m^3"),),
    "sliding": ((10.0, 1e6, " Pa/mm"),),  # tangential springs (no value: frictionless)
}


def _number(text: str, name: str, lo: float, hi: float, unit: str) -> float:
    try:
        v = float(text)
    except ValueError:
        raise EffectError(f"effect {name!r}: {text!r} is not a number") from None
    if not lo <= v <= hi:
        raise EffectError(f"effect {name!r}: value {v} outside the range [{lo}, {hi}]{unit}")
    return v


def _apply(eff: dict, name: str, value: str | None) -> None:
    if name == "sliding":
        eff["sliding"] = True
        if value not in (None, "true", "yes"):  # springs of this stiffness, Pa/mm
            eff["sliding_stiffness_pa_per_mm"] = _number(value, name, *_TWIN_RANGES[name][0])
        return
    value = value or EFFECTS[name]
    ranges = _TWIN_RANGES[name]
    if name == "skin":
        t, _, r = value.partition(":")
        eff["skin_thickness_mm"] = _number(t, name, *ranges[0])
        eff["skin_ratio"] = _number(r or "8", name, *ranges[1])
        return
    field = {"inclusions": "inclusion_ratio", "mooney": "c2_pa", "poisson": "nu",
             "density": "density_kg_m3"}[name]  # fmt: skip
    eff[field] = _number(value, name, *ranges[0])


def parse_effects(specs: list[str], *, default: TruthEffects) -> TruthEffects:
    """Parse ``NAME[=VALUE]`` strings (``skin=1.5:8`` is thickness mm : stiffness ratio).

    With no specs the preset's ``default`` is returned; ``none`` gives a neutral truth.

    Parameters
    ----------
    specs : list of str
        ``NAME`` or ``NAME=VALUE`` per effect, NAME one of ``none``, ``skin``
        (``THICKNESS_MM[:RATIO]``), ``sliding`` (none, ``true``/``yes``, or a tangential
        stiffness in Pa/mm), ``inclusions`` (stiffness ratio), ``mooney`` (c2 in Pa),
        ``poisson`` (nu) or ``density`` (kg/m^3); without a value each takes its
        default from :data:`EFFECTS`.
    default : TruthEffects
        Returned when ``specs`` is empty.

    Returns
    -------
    TruthEffects

    Raises
    ------
    EffectError
        An unknown or repeated name, an empty value after ``=``, a value that is not a
        number or lies outside the twin's range, or ``none`` given a value or combined
        with other effects.
    """
    if not specs:
        return default
    eff: dict = {}
    seen: set[str] = set()
    for spec in specs:
        name, sep, value = spec.partition("=")
        name = name.strip().lower()
        if name not in EFFECTS:
            raise EffectError(f"unknown effect {name!r}; choose from {', '.join(sorted(EFFECTS))}")
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


def truth_model(mesh: fem.TetMesh, c1_pa: float, effects: TruthEffects) -> fem.Model:
    """The truth model of a phantom mesh (regions bulk, inclusion, skin) with effects.

    Parameters
    ----------
    mesh : fem.TetMesh
        The phantom mesh (nodes in mm) with named regions.
    c1_pa : float
        Bulk neo-Hookean ``c1``, Pa.
    effects : TruthEffects
        The effects applied on top (:func:`parse_effects`).

    Returns
    -------
    fem.Model

    Raises
    ------
    ValueError
        A region of ``mesh`` has no material in the truth model.
    """
    unknown = []
    for name in mesh.region_names:
        try:
            region_fractions(name)
        except EffectError:
            unknown.append(name)
    if unknown:
        raise ValueError(f"truth model has no material for region(s) {sorted(unknown)}")
    return effect_model(mesh, c1_pa, effects.values(c1_pa))
