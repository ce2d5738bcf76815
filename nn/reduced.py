"""Our surrogate: a reduced basis of the displacement snapshots and a kernel over the load.

Input: the load vector ``b = rho g / c1`` (1/m, reference-scan frame), which is all the
FE solution depends on at a fixed Poisson ratio (``calib.sweep.plans``), scaled by the
largest training load: ``x = b / q_ref``. One vector carries the gravity direction and
the c1 axis, with no angle and so no seam at 0/360 deg.

Model (Eq. 1): ``u(x) = x L + k(x)^T alpha``, a linear term (the small-load, linear
elastic response, all three load directions) fitted by least squares to the training
snapshots, plus a kernel model of what it leaves (the nonlinearity): Gaussian-process
regression with a linear mean ("universal kriging"). With training directions on two
great circles only (the dissertation plan), the linear term still carries the response
to a load slightly off both planes (a registered scan's gravity is off its nominal plane
by a degree or so), where a kernel alone falls back to zero: on the quick twin it cuts
the error at the right lateral scan's gravity (0.5 deg off-plane) from 0.047 to 0.005 mm.

Kernel (Eq. 2): ``k(x, x') = exp(gamma (x . x' - 1)) - exp(-gamma)``, the exponential
dot-product kernel ``exp(gamma x . x')`` (positive definite on R^3; Steinwart &
Christmann 2008, Support Vector Machines, Lemma 4.8) less its constant term, times
``exp(-gamma)``. Every function of its span vanishes at ``x = 0``, so with the linear
term zero gravity gives exactly zero displacement; on the sphere ``|x| = 1`` it is the
Gaussian kernel ``exp(-gamma |x - x'|^2 / 2)`` up to a constant, smooth and rotation
invariant.

Fit: the displacement snapshots ``Y`` (S x 3N, mm) give a POD basis ``V_r`` (the right
singular vectors, no mean subtracted: a linear map keeps ``u(0) = 0``; Sirovich 1987,
Q. Appl. Math. 45:561) with ``r`` the smallest rank whose projection error on every
snapshot is below ``pod_tol_mm``. ``L`` solves ``X L = Y`` in the least-squares sense;
kernel ridge regression maps the load to the residual's POD coefficients and,
separately, the tumour-centre displacement's residual:
``u(x) = (x L + k(x)^T (K + lambda I)^{-1} (Y - X L)) V_r V_r^T``. ``gamma`` and
``lambda`` minimise the leave-one-out error of the kernel part (Eq. 3), computed in
closed form for each pair from one eigen-decomposition of ``K`` (Rifkin & Lippert 2007,
"Notes on regularized least squares", MIT-CSAIL-TR-2007-025:
``e_i = alpha_i / (H^{-1})_ii``). That closed form keeps the linear term fitted to every
scenario (optimistic: exactly 0 with three training loads, which ``L`` interpolates), so
the error reported at the chosen pair is the leave-one-out error of the whole model,
each scenario left out of ``L`` and the kernel alike (Eq. 4; review AM: a 9-scenario fit
reported 0.61 mm for a true 0.93).
"""

from __future__ import annotations

import time

import numpy as np

from .data import SweepData, training_scenarios
from .device import Device

__all__ = ["ReducedKernelFit", "fit_reduced_kernel"]

GAMMAS = np.geomspace(0.25, 400.0, 28)
RIDGES = np.array([1e-13, 1e-12, 1e-11, 1e-10, 1e-9, 1e-8, 1e-7, 1e-6])  # relative to mean diag


def _kernel(x: np.ndarray, z: np.ndarray, gamma: float) -> np.ndarray:
    """``exp(gamma (x.z - 1)) - exp(-gamma)``, (len(x), len(z)). Eq. (2)."""
    return np.exp(gamma * (x @ z.T - 1.0)) - np.exp(-gamma)


class ReducedKernelFit:
    """A fitted reduced-basis kernel surrogate (numpy arrays; see :meth:`module`).

    Attributes
    ----------
    centers : ndarray, shape (S, 3)
        Scaled training loads ``x``.
    lin_pod : ndarray, shape (3, r)
        Linear term of the POD coefficients (``L V_r``).
    coef_pod : ndarray, shape (S, r)
        Kernel weights of the POD coefficients.
    basis : ndarray, shape (3N, r)
        POD modes (orthonormal columns).
    lin_tumour : ndarray, shape (3, 3) or None
    coef_tumour : ndarray, shape (S, 3) or None
    gamma, ridge, q_ref_per_m, density_kg_m3 : float
    report : dict
    """

    def __init__(self, **kw):
        self.__dict__.update(kw)

    def predict_numpy(self, load_per_m: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
        """Vertex displacements (B, N, 3) and tumour (B, 3) for loads ``rho g / c1``."""
        x = np.atleast_2d(load_per_m) / self.q_ref_per_m
        k = _kernel(x, self.centers, self.gamma)
        u = (x @ self.lin_pod + k @ self.coef_pod) @ self.basis.T  # Eq. (1)
        t = None if self.coef_tumour is None else x @ self.lin_tumour + k @ self.coef_tumour
        return u.reshape(len(x), -1, 3), t

    def module(self):
        """The TorchScript-able module of this fit (see :mod:`nn.modules`)."""
        from .modules import ReducedKernelModule

        return ReducedKernelModule(self)


def _loo_errors(evals, evecs, Y, lambdas, n_nodes):
    """Mean vertex error (mm) of leave-one-out kernel predictions for each ridge. Eq. (3).

    ``evals, evecs``: eigen-decomposition of the kernel matrix ``K``; ``Y`` (S, 3N) the
    fitted values (here the residual of the linear term, fitted to all scenarios: a
    slightly optimistic estimate, used only to choose ``gamma`` and ``lambda``).
    """
    QtY = evecs.T @ Y
    out = []
    for lam in lambdas:
        d = 1.0 / (evals + lam)
        alpha = evecs @ (d[:, None] * QtY)
        hinv_diag = np.einsum("ij,j,ij->i", evecs, d, evecs)
        e = (alpha / hinv_diag[:, None]).reshape(len(Y), n_nodes, 3)
        out.append(float(np.linalg.norm(e, axis=2).mean()))
    return np.array(out)


def _loo_model_error(X, C, V, Y, gamma: float, ridge: float) -> float:
    """Mean vertex error (mm) of the whole model refitted without each scenario. Eq. (4).

    ``X`` (S, 3) scaled loads, ``C = Y V`` (S, r) the snapshots' POD coefficients, ``V``
    (3N, r) the basis, ``Y`` (S, 3N) the snapshots. A prediction from the other
    scenarios lies in their span, inside ``V``'s, so it is formed in POD coordinates and
    compared with the snapshot itself in full.

    Each scenario ``i`` is left out of the linear term (``L_i``, least squares on the
    others: a 3-column fit) and of the kernel ridge regression on what that term leaves
    of the others, ``C - X L_i``. The kernel's prediction without ``i`` follows from the
    whole kernel matrix in closed form for any targets (Rasmussen & Williams 2006,
    Gaussian Processes for Machine Learning, Eq. 5.12): ``t_i - [H^-1 t]_i / [H^-1]_ii``
    with ``H = K + ridge I``, whatever ``t_i`` is. With ``t = C - X L_i`` the linear
    term's part at ``i`` cancels and the model's error in POD coordinates is (Eq. 5)

        ``d_i = -([H^-1 C]_i - [H^-1 X]_i L_i) / [H^-1]_ii``,

    so one eigen-decomposition of ``K`` serves every ``i``: O(S^3), where a refit per
    scenario was O(S^4) (at 1000 scenarios on one core 0.20 s against 25.8 s:
    ``benchmarks/bench_surrogate_fit.py``).
    """
    S = len(X)
    evals, evecs = np.linalg.eigh(_kernel(X, X, gamma))
    d = 1.0 / (evals + ridge)
    h = np.einsum("ij,j,ij->i", evecs, d, evecs)  # diag(H^-1)
    HC = evecs @ (d[:, None] * (evecs.T @ C))  # H^-1 C, (S, r)
    HX = evecs @ (d[:, None] * (evecs.T @ X))  # H^-1 X, (S, 3)
    delta = np.empty_like(HC)
    keep = np.ones(S, bool)
    for i in range(S):
        keep[i] = False
        L_i = np.linalg.lstsq(X[keep], C[keep], rcond=None)[0]  # (3, r)
        keep[i] = True
        delta[i] = -(HC[i] - HX[i] @ L_i) / h[i]  # Eq. (5)
    errs = np.empty(S)
    step = max(1, 2**22 // max(1, Y.shape[1]))  # rows of (S, 3N) at a time: ~32 MB
    for a in range(0, S, step):
        b = min(S, a + step)
        e = (C[a:b] + delta[a:b]) @ V.T - Y[a:b]
        errs[a:b] = np.linalg.norm(e.reshape(b - a, -1, 3), axis=2).mean(axis=1)
    return float(errs.mean())


def _pod(Y: np.ndarray, tol_mm: float) -> np.ndarray:
    """Smallest POD basis projecting every snapshot within ``tol_mm`` at every vertex."""
    _, s, vt = np.linalg.svd(Y, full_matrices=False)
    V = vt.T
    coeff = Y @ V
    for r in range(1, len(s) + 1):
        resid = Y - coeff[:, :r] @ V[:, :r].T
        if np.linalg.norm(resid.reshape(len(Y), -1, 3), axis=2).max() <= tol_mm:
            return V[:, :r]
    return V


def fit_reduced_kernel(
    data: SweepData,
    *,
    device: Device = "auto",
    pod_tol_mm: float = 1e-4,
    progress=None,
) -> ReducedKernelFit:
    """Fit our surrogate on the training scenarios of a sweep (see the module docstring).

    Parameters
    ----------
    data : SweepData
        Its ``role == "train"`` scenarios are fitted; the others are reported.
    device : {"auto", "cpu", "cuda"}
        Where the kernel algebra runs (float64; deterministic either way).
    pod_tol_mm : float
        Largest projection error of a training snapshot on the POD basis.
    progress : callable, optional
        Called with a line of text.

    Returns
    -------
    ReducedKernelFit
    """
    from .device import select_device

    say = progress or (lambda _m: None)
    dev = select_device(device)
    t0 = time.perf_counter()
    train = training_scenarios(data)
    q_ref = float(np.linalg.norm(train.load_per_m, axis=1).max())
    X = train.load_per_m / q_ref
    N = len(data.nodes_mm)
    Y = train.displacement_mm.reshape(len(train), -1)
    V = _pod(Y, pod_tol_mm)
    say(f"POD: {V.shape[1]} modes of {len(train)} snapshots (projection error <= {pod_tol_mm} mm)")
    L = np.linalg.lstsq(X, Y, rcond=None)[0]  # (3, 3N): the linear term of Eq. (1)
    R = Y - X @ L
    best = (np.inf, None, None)
    for gamma in GAMMAS:
        K = _kernel(X, X, gamma)
        evals, evecs = _eigh(K, dev)
        scale = float(np.mean(np.diag(K)))
        errs = _loo_errors(evals, evecs, R, RIDGES * scale, N)
        j = int(np.argmin(errs))
        if errs[j] < best[0]:
            best = (float(errs[j]), float(gamma), float(RIDGES[j] * scale))
    _, gamma, ridge = best
    loo = _loo_model_error(X, Y @ V, V, Y, gamma, ridge)
    say(
        f"kernel: gamma {gamma:.3g}, ridge {ridge:.3g} (leave-one-out mean error {loo:.4f} "
        "mm, each training scenario left out of the whole fit)"
    )
    K = _kernel(X, X, gamma)
    H = K + ridge * np.eye(len(X))
    coef_pod = _solve(H, R @ V, dev)
    lin_t = coef_t = None
    if data.has_tumour:
        lin_t = np.linalg.lstsq(X, train.tumour_mm, rcond=None)[0]
        coef_t = _solve(H, train.tumour_mm - X @ lin_t, dev)
    fit = ReducedKernelFit(
        centers=X,
        lin_pod=L @ V,
        coef_pod=coef_pod,
        basis=V,
        lin_tumour=lin_t,
        coef_tumour=coef_t,
        gamma=gamma,
        ridge=ridge,
        q_ref_per_m=q_ref,
        density_kg_m3=float(data.model["density_kg_m3"]),
        report={
            "kind": "ours",
            "method": "POD; linear term + kernel ridge regression on the load rho g / c1",
            "device": str(dev),
            "n_train": len(train),
            "pod_modes": int(V.shape[1]),
            "pod_tol_mm": pod_tol_mm,
            "gamma": gamma,
            "ridge": ridge,
            "loo_mean_error_mm": loo,
            "train_wall_s": time.perf_counter() - t0,
        },
    )
    return fit


def _eigh(K: np.ndarray, dev):
    import torch

    w, v = torch.linalg.eigh(torch.as_tensor(K, dtype=torch.float64, device=dev))
    return w.cpu().numpy(), v.cpu().numpy()


def _solve(H: np.ndarray, B: np.ndarray, dev) -> np.ndarray:
    import torch

    Ht = torch.as_tensor(H, dtype=torch.float64, device=dev)
    Bt = torch.as_tensor(B, dtype=torch.float64, device=dev)
    L = torch.linalg.cholesky(Ht)
    return torch.cholesky_solve(Bt, L).cpu().numpy()
