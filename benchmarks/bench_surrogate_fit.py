"""Training cost of our surrogate as the sweep grows: the reported leave-one-out error.

``surrogate train --kind ours`` reports the leave-one-out error of the whole model, each
training scenario left out of the linear term and the kernel alike
(:func:`nn.reduced._loo_model_error`, Eq. 5 there). It was computed by refitting the
model without each scenario, S solves of S - 1 kernel equations: O(S^4), 30 s at 1000
scenarios on one core. It is now one eigen-decomposition of the kernel matrix and a
3-column least squares per scenario, O(S^3). This prints, per number of training
scenarios S, the closed form's time against that refit per scenario (the peer, the same
loop as ``tests/nn/test_nn_surrogate.py``'s reference) measured in the same run, their
difference (mm), and the whole fit's time (``nn.reduced.fit_reduced_kernel``: the
kernel's width and ridge chosen over 28 x 8 pairs, then the leave-one-out error).

The data are synthetic and smooth (the loads of random directions and c1 values, a
field linear and quadratic in the load at ``--nodes`` vertices, as
``test_kernel_recovers_a_smooth_field_with_a_c1_axis``): the algebra's cost depends on
S, the vertices and the POD rank only, not on the FE solutions.

    python benchmarks/bench_surrogate_fit.py [--sizes 125,250,500,1000] [--repeat 3]
                                             [--nodes 384] [--peer-max 1000] [--seed 0]

Each time is the median of ``--repeat`` runs with its range; the peer is skipped above
``--peer-max`` scenarios (O(S^4): about 8 minutes a run at 2000).
"""

from __future__ import annotations

import argparse
import time
from functools import partial

import numpy as np
from _provenance import print_header


def synthetic_sweep(n_scenarios: int, n_nodes: int, seed: int):
    """A SweepData of ``n_scenarios`` training loads and a smooth field at ``n_nodes``."""
    from nn.data import SweepData

    rng = np.random.default_rng(seed)
    dirs = rng.normal(size=(n_scenarios, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    c1 = rng.uniform(400.0, 800.0, n_scenarios)
    b = 1000.0 * 9.81 * dirs / c1[:, None]
    A, n = rng.normal(size=(n_nodes, 3, 3)), rng.normal(size=3)
    m, q = rng.normal(size=(n_nodes, 3)), rng.normal(size=(3, 3))  # m: a shape per vertex
    u = np.einsum("nij,bj->bni", A, b) * 0.4  # linear in the load: ~5 mm, as the twin's
    u += ((b @ n) ** 2)[:, None, None] * m * 4e-4  # and beyond it, at every vertex
    u += np.sin(b @ q * 0.05)[:, None, :] * m[None] * 0.4
    return SweepData(
        path=None,
        nodes_mm=np.zeros((n_nodes, 3)),
        tets=np.zeros((0, 4), int),
        surface_nodes=np.arange(n_nodes),
        back_nodes=np.zeros(0, int),
        boundary_faces=np.zeros((0, 3), int),
        index=np.arange(n_scenarios),
        gravity_ref=dirs,
        gravity_phantom=dirs,
        c1_pa=c1,
        load_per_m=b,
        role=np.full(n_scenarios, "train"),
        plane=np.full(n_scenarios, "sphere"),
        angle_deg=np.full(n_scenarios, np.nan),
        displacement_mm=u,
        tumour_mm=u[:, 0],
        nipple_mm=u[:, 1],
        model={"density_kg_m3": 1000.0},
        mesh_sha256="",
    )


def refit_per_scenario(X, C, V, Y, gamma: float, ridge: float) -> float:
    """The peer: the whole model refitted without each scenario (O(S^4))."""
    from nn.reduced import _kernel

    K = _kernel(X, X, gamma)
    errs = []
    for i in range(len(X)):
        keep = np.arange(len(X)) != i
        L = np.linalg.lstsq(X[keep], C[keep], rcond=None)[0]
        H = K[np.ix_(keep, keep)] + ridge * np.eye(len(X) - 1)
        alpha = np.linalg.solve(H, C[keep] - X[keep] @ L)
        e = ((X[i] @ L + K[i, keep] @ alpha) @ V.T - Y[i]).reshape(-1, 3)
        errs.append(np.linalg.norm(e, axis=1).mean())
    return float(np.mean(errs))


def timed(fn, args: tuple, repeat: int) -> tuple[float, float, float, object]:
    """Median, min and max wall time (s) of ``repeat`` calls ``fn(*args)``, the last value."""
    times, value = [], None
    for _ in range(repeat):
        t = time.perf_counter()
        value = fn(*args)
        times.append(time.perf_counter() - t)
    return float(np.median(times)), min(times), max(times), value


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", default="125,250,500,1000")
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--nodes", type=int, default=384)
    ap.add_argument("--peer-max", type=int, default=1000)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    sizes = [int(s) for s in args.sizes.split(",")]
    if args.repeat < 1 or min(sizes) < 4 or args.nodes < 1:
        ap.error("--repeat >= 1, every size >= 4 and --nodes >= 1")
    print_header(("numpy", "torch"))
    from nn.reduced import _loo_model_error, fit_reduced_kernel

    print(
        f"synthetic sweeps, {args.nodes} vertices, seed {args.seed}; times in s, median "
        f"of {args.repeat} (range)\n"
    )
    print("| S | POD modes | leave-one-out error mm | closed form s | refit per scenario s "
          "(peer) | peer / ours | difference mm | whole fit s |")  # fmt: skip
    print("|---|---|---|---|---|---|---|---|")
    for S in sizes:
        data = synthetic_sweep(S, args.nodes, args.seed)
        fit = fit_reduced_kernel(data, device="cpu")
        X = data.load_per_m / fit.q_ref_per_m
        Y = data.displacement_mm.reshape(S, -1)
        V = fit.basis
        C = Y @ V
        ours = timed(_loo_model_error, (X, C, V, Y, fit.gamma, fit.ridge), args.repeat)
        whole = timed(partial(fit_reduced_kernel, device="cpu"), (data,), args.repeat)
        if S <= args.peer_max:
            peer = timed(refit_per_scenario, (X, C, V, Y, fit.gamma, fit.ridge), args.repeat)
            peer_s = f"{peer[0]:.3g} ({peer[1]:.3g}-{peer[2]:.3g})"
            ratio = f"{peer[0] / ours[0]:.0f}"
            diff = f"{abs(ours[3] - peer[3]):.1e}"
        else:
            peer_s, ratio, diff = "not run", "", ""
        print(
            f"| {S} | {V.shape[1]} | {ours[3]:.2g} | {ours[0]:.3g} ({ours[1]:.3g}-{ours[2]:.3g}) "
            f"| {peer_s} | {ratio} | {diff} | {whole[0]:.3g} ({whole[1]:.3g}-{whole[2]:.3g}) |",
            flush=True,
        )


if __name__ == "__main__":
    main()
