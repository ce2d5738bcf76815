"""TorchScript-able surrogate modules: ``forward(gravity_ref_m_s2, c1_pa) -> dict``.

Both modules take the gravity acceleration vector in the reference-scan (model) frame,
m/s^2, shape (B, 3), and c1 in Pa, shape (B,), and return a dict of tensors (mm): ours
``nodes_mm`` (B, N, 3, every vertex; float32 by default) and ``tumour_mm`` (B, 3,
float64); the dissertation baseline ``surface_mm`` (B, n_surface, 3) and ``tumour_mm``
(float64 from its float32 networks). The mesh they
were trained on travels with them as buffers (``mesh_nodes_mm``, ``mesh_tets``,
``mesh_boundary_faces``, ``surface_nodes``, ``back_nodes``).
"""

# no "from __future__ import annotations": TorchScript reads the annotations
from typing import TYPE_CHECKING

import torch

if TYPE_CHECKING:
    from .data import SweepData
    from .reduced import ReducedKernelFit

__all__ = ["DissertationMLPModule", "ReducedKernelModule", "mlp"]


def _f64(a) -> torch.Tensor:
    return torch.as_tensor(a, dtype=torch.float64).clone()


def _register_mesh(module: torch.nn.Module, data: "SweepData") -> None:
    module.register_buffer("mesh_nodes_mm", _f64(data.nodes_mm))
    module.register_buffer("mesh_tets", torch.as_tensor(data.tets, dtype=torch.int64).clone())
    module.register_buffer(
        "mesh_boundary_faces", torch.as_tensor(data.boundary_faces, dtype=torch.int64).clone()
    )
    module.register_buffer(
        "surface_nodes", torch.as_tensor(data.surface_nodes, dtype=torch.int64).clone()
    )
    module.register_buffer(
        "back_nodes", torch.as_tensor(data.back_nodes, dtype=torch.int64).clone()
    )


class ReducedKernelModule(torch.nn.Module):
    """Ours at query time: ``u = (x L_r + k(x) A) V^T`` with ``x = rho g / (c1 q_ref)``.

    See :mod:`nn.reduced` for the kernel and the fit.
    """

    gamma: float
    exp_neg_gamma: float
    load_scale: float
    has_tumour: bool
    n_nodes: int

    def __init__(
        self,
        fit: "ReducedKernelFit",
        data: "SweepData | None" = None,
        *,
        basis_dtype: torch.dtype = torch.float32,
    ):
        super().__init__()
        import math

        self.gamma = float(fit.gamma)
        self.exp_neg_gamma = math.exp(-self.gamma)
        self.load_scale = float(fit.density_kg_m3 / fit.q_ref_per_m)
        self.n_nodes = int(fit.basis.shape[0] // 3)
        self.register_buffer("centers", _f64(fit.centers))
        self.register_buffer("lin_pod", _f64(fit.lin_pod))
        self.register_buffer("coef_pod", _f64(fit.coef_pod))
        # the POD expansion, the bulk of the work, in float32 by default (6x the batched
        # throughput; 1e-7 relative, ~1e-6 mm): the kernel and coefficients stay float64
        self.register_buffer("basis_t", _f64(fit.basis.T).to(basis_dtype).contiguous())
        self.has_tumour = fit.coef_tumour is not None
        tumour = fit.coef_tumour if self.has_tumour else torch.zeros(len(fit.centers), 3)
        lin_t = fit.lin_tumour if self.has_tumour else torch.zeros(3, 3)
        self.register_buffer("coef_tumour", _f64(tumour))
        self.register_buffer("lin_tumour", _f64(lin_t))
        if data is not None:
            _register_mesh(self, data)

    def forward(
        self, gravity_ref_m_s2: torch.Tensor, c1_pa: torch.Tensor
    ) -> dict[str, torch.Tensor]:
        """Vertex and tumour-centre displacements (mm) for a batch of loads."""
        g = gravity_ref_m_s2.to(torch.float64)
        c1 = c1_pa.to(torch.float64).reshape(-1, 1)
        x = g * (self.load_scale / c1)  # Eq. (1) of nn.reduced: x = rho g / (c1 q_ref)
        k = torch.exp(self.gamma * (x @ self.centers.t() - 1.0)) - self.exp_neg_gamma
        coef = (x @ self.lin_pod + k @ self.coef_pod).to(self.basis_t.dtype)  # Eq. (1)
        nodes = (coef @ self.basis_t).reshape(-1, self.n_nodes, 3)
        out = {"nodes_mm": nodes}
        if self.has_tumour:
            out["tumour_mm"] = x @ self.lin_tumour + k @ self.coef_tumour
        return out


def mlp(sizes: list[int]) -> torch.nn.Sequential:
    """ReLU MLP with Glorot-uniform weights and zero biases (Keras ``Dense`` defaults)."""
    layers: list[torch.nn.Module] = []
    for k in range(len(sizes) - 1):
        lin = torch.nn.Linear(sizes[k], sizes[k + 1])
        torch.nn.init.xavier_uniform_(lin.weight)
        torch.nn.init.zeros_(lin.bias)
        layers.append(lin)
        if k < len(sizes) - 2:
            layers.append(torch.nn.ReLU())
    return torch.nn.Sequential(*layers)


class DissertationMLPModule(torch.nn.Module):
    """The dissertation's two MLPs: unit gravity (and c1) to surface nodes and tumour.

    Surface: 2 hidden layers of 60 ReLU units; tumour: 1 hidden layer of 20 (chapter 3.6).
    Input: the unit gravity direction (reference frame), plus ``c1 / c1_ref`` when the
    sweep has a c1 axis (the dissertation's fourth input was a material ratio). A zero
    gravity vector has no direction: the output is set to zero there.
    """

    with_c1: bool
    c1_ref: float
    n_surface: int
    has_tumour: bool

    def __init__(self, n_surface: int, *, with_c1: bool, c1_ref: float, has_tumour: bool):
        super().__init__()
        n_in = 4 if with_c1 else 3
        self.with_c1, self.c1_ref, self.n_surface = with_c1, float(c1_ref), int(n_surface)
        self.has_tumour = has_tumour
        self.surface_net = mlp([n_in, 60, 60, 3 * n_surface])
        self.tumour_net = mlp([n_in, 20, 3])

    def features(self, gravity_ref_m_s2: torch.Tensor, c1_pa: torch.Tensor) -> torch.Tensor:
        """Network input (float32): unit direction, and ``c1 / c1_ref`` with a c1 axis."""
        g = gravity_ref_m_s2.to(torch.float32)
        norm = torch.linalg.vector_norm(g, dim=1, keepdim=True)
        d = g / torch.clamp(norm, min=1e-30)
        if self.with_c1:
            d = torch.cat([d, c1_pa.to(torch.float32).reshape(-1, 1) / self.c1_ref], dim=1)
        return d

    def forward(
        self, gravity_ref_m_s2: torch.Tensor, c1_pa: torch.Tensor
    ) -> dict[str, torch.Tensor]:
        """Surface-node and tumour-centre displacements (mm) for a batch of gravities."""
        f = self.features(gravity_ref_m_s2, c1_pa)
        loaded = (torch.linalg.vector_norm(gravity_ref_m_s2, dim=1) > 0).to(torch.float64)
        s = self.surface_net(f).to(torch.float64).reshape(-1, self.n_surface, 3)
        out = {"surface_mm": s * loaded.reshape(-1, 1, 1)}
        if self.has_tumour:
            out["tumour_mm"] = self.tumour_net(f).to(torch.float64) * loaded.reshape(-1, 1)
        return out
