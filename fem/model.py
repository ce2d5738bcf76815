"""The model description: mesh, a material and density per region, and the support.

A physical effect is added by describing it here — a new region with its own
material (a skin layer, stiff inclusions), another material law, another density,
another support of the back plane — never by changing the solver.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from types import MappingProxyType
from typing import Literal

import numpy as np

from .materials import Material
from .mesh import MeshError, TetMesh
from .units import DEFAULT_DENSITY_KG_M3

__all__ = ["Clamped", "Constrained", "ElasticSupport", "Model", "Sliding", "Support"]


@dataclass(frozen=True)
class Clamped:
    """All displacement components fixed on a node set (the dissertation's back plane).

    Attributes
    ----------
    node_set : str
        Name of the mesh's node set whose boundary faces are held (every displacement
        dof on those faces, P2 mid-side ones included).
    """

    node_set: str = "back"


@dataclass(frozen=True)
class Sliding:
    """Normal displacement fixed on a planar node set; the face slides in its plane.

    A sliding face alone cannot carry an in-plane load, so by default the rim of the
    face (its boundary edge) is held in the plane as well (``hold="rim"``), as a
    phantom glued at its perimeter. ``hold="none"`` leaves the in-plane motion to
    ``tangent_stiffness_pa_per_mm`` springs, which must then be positive.

    Attributes
    ----------
    node_set : str
        Name of the mesh's node set holding the (planar) face; its least-squares plane's
        outward normal is the direction held.
    hold : {"rim", "none"}
        ``"rim"``: the face's rim (its boundary edge, P2 mid-side dofs included) is held
        in the plane too, so it does not move; ``"none"``: only the springs resist
        in-plane motion.
    tangent_stiffness_pa_per_mm : float
        In-plane springs on the face per unit area (traction in Pa per mm of tangential
        displacement); 0 for none (only with ``hold="rim"``).
    """

    node_set: str = "back"
    hold: Literal["rim", "none"] = "rim"
    tangent_stiffness_pa_per_mm: float = 0.0

    def __post_init__(self) -> None:
        if self.hold not in ("rim", "none"):
            raise ValueError(f"Sliding.hold must be 'rim' or 'none', got {self.hold!r}")
        if self.hold == "none" and not self.tangent_stiffness_pa_per_mm > 0:
            raise ValueError("Sliding(hold='none') needs tangent_stiffness_pa_per_mm > 0")


@dataclass(frozen=True)
class ElasticSupport:
    """Distributed springs on a face: traction = -k u (stiffness per area, Pa/mm).

    Attributes
    ----------
    node_set : str
        Name of the mesh's node set holding the (planar) face; normal and tangent are
        those of its least-squares plane.
    normal_stiffness_pa_per_mm : float
        Spring stiffness per unit area along the face's normal: traction in Pa per mm of
        normal displacement (> 0).
    tangent_stiffness_pa_per_mm : float
        The same in the face's plane, Pa/mm (>= 0).
    """

    node_set: str = "back"
    normal_stiffness_pa_per_mm: float = 1.0e3
    tangent_stiffness_pa_per_mm: float = 1.0e3

    def __post_init__(self) -> None:
        if self.normal_stiffness_pa_per_mm <= 0 or self.tangent_stiffness_pa_per_mm < 0:
            raise ValueError("ElasticSupport needs normal stiffness > 0 and tangent >= 0")


@dataclass(frozen=True)
class Constrained:
    """Chosen displacement components (model-frame axes 0, 1, 2) fixed on a node set.

    Used for symmetry planes and for prescribed displacements (see ``fem.solve``).

    Attributes
    ----------
    node_set : str
        Name of the mesh's node set (its vertices and the P2 mid-side dofs of the edges
        between them are held).
    components : tuple of int
        The fixed displacement components, a non-empty subset of (0, 1, 2): the model
        frame's x, y, z (the mesh's own axes).
    """

    node_set: str
    components: tuple[int, ...] = (0, 1, 2)

    def __post_init__(self) -> None:
        if not set(self.components) <= {0, 1, 2} or not self.components:
            raise ValueError(f"components must be a subset of (0, 1, 2), got {self.components}")


Support = Clamped | Sliding | ElasticSupport | Constrained


def as_supports(support) -> tuple:
    """A support or a tuple of supports, as a tuple."""
    return tuple(support) if isinstance(support, (tuple, list)) else (support,)


@dataclass(frozen=True)
class Model:
    """Everything the solver needs besides the load.

    Parameters
    ----------
    mesh : TetMesh
        Geometry in mm, with region tags and the support's node set.
    materials : mapping of str to Material
        Material law of each region present in the mesh.
    density_kg_m3 : mapping of str to float
        Density of each region in kg/m^3.
    support : Support or tuple of Support
        How the back plane is held (``Clamped``, ``Sliding``, ``ElasticSupport``),
        possibly with extra ``Constrained`` node sets.
    """

    mesh: TetMesh
    materials: Mapping[str, Material]
    density_kg_m3: Mapping[str, float]
    support: Support | tuple = field(default_factory=Clamped)

    def __post_init__(self) -> None:
        object.__setattr__(self, "materials", MappingProxyType(dict(self.materials)))
        object.__setattr__(self, "density_kg_m3", MappingProxyType(dict(self.density_kg_m3)))
        present = {n for n, t in self.mesh.region_names.items() if np.any(self.mesh.region == t)}
        unnamed = set(np.unique(self.mesh.region)) - set(self.mesh.region_names.values())
        if unnamed:
            raise MeshError(f"element region tags {sorted(unnamed)} have no name")
        for what, table in (("material", self.materials), ("density", self.density_kg_m3)):
            missing = present - set(table)
            if missing:
                raise ValueError(f"no {what} given for region(s) {sorted(missing)}")
        for name, rho in self.density_kg_m3.items():
            if not rho > 0:
                raise ValueError(f"density of region {name!r} must be positive, got {rho}")
        for sup in as_supports(self.support):
            self.mesh.node_set(sup.node_set)

    @classmethod
    def homogeneous(
        cls,
        mesh: TetMesh,
        material: Material,
        *,
        density_kg_m3: float = DEFAULT_DENSITY_KG_M3,
        support: Support | None = None,
    ) -> Model:
        """One material and density for every region of the mesh."""
        names = list(mesh.region_names)
        return cls(
            mesh,
            {n: material for n in names},
            {n: density_kg_m3 for n in names},
            support if support is not None else Clamped(),
        )

    def with_material(self, region: str, material: Material) -> Model:
        """A copy with the material of one region replaced."""
        return replace(self, materials={**self.materials, region: material})

    def with_support(self, support: Support) -> Model:
        """A copy with another support."""
        return replace(self, support=support)

    def with_mesh(self, mesh: TetMesh) -> Model:
        """A copy on another mesh (same region names)."""
        return replace(self, mesh=mesh)

    def element_material_groups(self):
        """Yield ``(element_indices, material, density)``, regions of equal law merged.

        Regions that share one material object (or an equal one) and one density are
        assembled as a single group, so a homogeneous model is one vectorised pass.
        """
        groups: dict = {}
        for name, tag in self.mesh.region_names.items():
            idx = np.flatnonzero(self.mesh.region == tag)
            if idx.size:
                key = (_hashable(self.materials[name]), self.density_kg_m3[name])
                groups.setdefault(key, []).append(idx)
        for (material, rho), parts in groups.items():
            law = material.obj if isinstance(material, _ByIdentity) else material
            yield np.sort(np.concatenate(parts)), law, rho


@dataclass(frozen=True, eq=False)
class _ByIdentity:
    obj: object

    def __hash__(self) -> int:
        return id(self.obj)

    def __eq__(self, other) -> bool:
        return isinstance(other, _ByIdentity) and other.obj is self.obj


def _hashable(material):
    """The material itself as a dict key when hashable, else a by-identity wrapper."""
    try:
        hash(material)
    except TypeError:
        return _ByIdentity(material)
    return material
