"""The dissertation's surrogate, reproduced as the baseline (chapters 3.6 and 4.4).

Two fully connected ReLU networks from the unit gravity vector: one to the surface nodal
displacements (2 hidden layers of 60 units), one to the tumour-centre displacement (1
hidden layer of 20 units). Trained as described: Adam with learning rate 1e-5 (Keras
defaults otherwise, ``eps = 1e-7``), mean absolute error loss (Eq. 3.16), 30 000
iterations, hold-out validation with a random 80 / 20 split of the training scenarios;
Glorot-uniform weights and zero biases (TensorFlow's ``Dense`` defaults), float32,
full batch (fewer than 32 scenarios: one Keras batch per epoch). Outputs in mm, not
normalised (the text mentions no scaling).
"""

from __future__ import annotations

import time

import numpy as np

from .data import SweepData, training_scenarios
from .device import Device

__all__ = ["DISSERTATION_REPORTED", "DissertationFit", "fit_dissertation_mlps"]

#: What the dissertation reports of its MLPs against FE on its 48 validation directions
#: (chapter 4.5): the surface error's mean and sd and the tumour centre's largest error,
#: mm, and the time of one prediction, ms. Published figures, not measured here.
DISSERTATION_REPORTED = {
    "surface_mean_mm": 0.19,
    "surface_sd_mm": 0.12,
    "tumour_max_mm": 0.22,
    "query_ms": 5.0,
}


class DissertationFit:
    """The trained baseline: its module (:class:`nn.modules.DissertationMLPModule`) and report."""

    def __init__(self, module, report: dict):
        self._module, self.report = module, report

    def module(self):
        """The trained module (on the CPU)."""
        return self._module


def fit_dissertation_mlps(
    data: SweepData,
    *,
    iterations: int = 30_000,
    learning_rate: float = 1e-5,
    test_fraction: float = 0.2,
    device: Device = "auto",
    seed: int = 0,
    progress=None,
) -> DissertationFit:
    """Train the dissertation's two MLPs on the training scenarios of a sweep.

    Parameters
    ----------
    data : SweepData
    iterations : int
        Adam steps (full batch); the dissertation's 30 000 by default.
    learning_rate : float
    test_fraction : float
        Share of the training scenarios held out as the "testing" set.
    device : {"auto", "cpu", "cuda"}
    seed : int
        Seed of the split and the initial weights.
    progress : callable, optional
        Called with a line of text every 5 000 iterations.

    Returns
    -------
    DissertationFit
    """
    import torch

    from .device import deterministic, select_device
    from .modules import DissertationMLPModule, _register_mesh

    say = progress or (lambda _m: None)
    dev = select_device(device)
    train = training_scenarios(data)
    n = len(train)
    perm = np.random.default_rng(seed).permutation(n)
    n_test = int(round(test_fraction * n))
    test_idx, fit_idx = np.sort(perm[:n_test]), np.sort(perm[n_test:])
    c1s = np.unique(train.c1_pa)
    g = float(data.model["g_m_s2"])
    t0 = time.perf_counter()
    with deterministic(seed):
        module = DissertationMLPModule(
            len(data.surface_nodes),
            with_c1=len(c1s) > 1,
            c1_ref=float(data.model["c1_pa"]),
            has_tumour=data.has_tumour,
        )
        _register_mesh(module, data)
        module = module.to(dev)
        fit = train.subset(fit_idx)
        X = module.features(
            torch.as_tensor(fit.gravity_ref * g, device=dev), torch.as_tensor(fit.c1_pa, device=dev)
        )
        Ys = torch.as_tensor(
            fit.displacement_mm[:, data.surface_nodes].reshape(len(fit), -1),
            dtype=torch.float32,
            device=dev,
        )
        Yt = torch.as_tensor(fit.tumour_mm, dtype=torch.float32, device=dev)
        nets = [(module.surface_net, Ys)] + ([(module.tumour_net, Yt)] if data.has_tumour else [])
        opts = [torch.optim.Adam(net.parameters(), lr=learning_rate, eps=1e-7) for net, _ in nets]
        initial = [[p.detach().clone() for p in net.parameters()] for net, _ in nets]
        loss_fn = torch.nn.L1Loss()
        history = []
        for it in range(1, iterations + 1):
            losses = []
            for (net, Y), opt in zip(nets, opts, strict=True):
                opt.zero_grad(set_to_none=True)
                loss = loss_fn(net(X), Y)
                loss.backward()
                opt.step()
                losses.append(loss)
            if it == 1 or it % 1000 == 0 or it == iterations:
                row = [it] + [float(v.detach()) for v in losses]
                history.append(row)
                if it % 5000 == 0 or it == iterations:
                    say(
                        f"iteration {it}: MAE surface {row[1]:.4f} mm"
                        + (f", tumour {row[2]:.4f} mm" if len(row) > 2 else "")
                    )
        moved = [
            max(
                float((p.detach() - p0).abs().max())
                for p, p0 in zip(net.parameters(), w0, strict=True)
            )
            for (net, _), w0 in zip(nets, initial, strict=True)
        ]
    module = module.to("cpu").eval()
    wall = time.perf_counter() - t0
    report = {
        "kind": "dissertation",
        "method": "two ReLU MLPs (60-60 surface, 20 tumour), Adam lr 1e-5, MAE, full batch",
        "device": str(dev),
        # review BI: on the CPU torch's reductions follow its thread count, so training is
        # reproducible at equal counts only (one step's gradients differ by ~1e-7 between
        # 1 and 2 threads)
        "torch_threads": int(torch.get_num_threads()),
        "n_train": int(len(fit_idx)),
        "n_test": int(len(test_idx)),
        "test_scenarios": [int(i) for i in train.index[test_idx]],
        "iterations": int(iterations),
        "learning_rate": learning_rate,
        "seed": int(seed),
        "loss_history": history,
        # how far training moved each net's weights (the largest change of any weight; the
        # README's reading of why the tumour net does not converge at lr 1e-5)
        "max_weight_change": dict(zip(("surface", "tumour"), moved, strict=False)),
        "train_wall_s": wall,
        "s_per_1000_iterations": wall / max(iterations, 1) * 1000,
    }
    return DissertationFit(module, report)
