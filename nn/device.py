"""Device choice and deterministic torch settings for training.

Training is seeded and runs with ``torch.use_deterministic_algorithms(True)``; on CUDA
cuBLAS needs ``CUBLAS_WORKSPACE_CONFIG`` for that (set here when unset). The previous
global settings are restored when training ends.
"""

from __future__ import annotations

import contextlib
import os
from typing import Literal

__all__ = ["Device", "deterministic", "select_device"]

Device = Literal["auto", "cpu", "cuda"]


def select_device(device: Device | str = "auto"):
    """The torch device to train on: ``auto`` takes CUDA when present, else the CPU.

    Parameters
    ----------
    device : {"auto", "cpu", "cuda"}

    Returns
    -------
    torch.device

    Raises
    ------
    ValueError
        An unknown name, or ``cuda`` without a CUDA device.
    """
    import torch

    if device == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if device == "cpu":
        return torch.device("cpu")
    if device == "cuda":
        if not torch.cuda.is_available():
            raise ValueError(
                "device (--device) cuda: no CUDA device (torch has no GPU here); use auto"
            )
        return torch.device("cuda")
    raise ValueError(f"device (--device) must be auto, cpu or cuda, got {device!r}")


@contextlib.contextmanager
def deterministic(seed: int):
    """Seed torch and turn on deterministic algorithms for the duration of a block."""
    import torch

    os.environ.setdefault("CUBLAS_WORKSPACE_CONFIG", ":4096:8")
    was = torch.are_deterministic_algorithms_enabled()
    state = torch.random.get_rng_state()
    torch.use_deterministic_algorithms(True)
    torch.manual_seed(seed)
    try:
        yield
    finally:
        torch.use_deterministic_algorithms(was)
        torch.random.set_rng_state(state)
