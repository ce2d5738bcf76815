"""The digital twin: synthetic multi-posture scan sets with sealed truth.

Only the twin (and tests and benchmarks) may read ``OUT/truth/``; the pipeline
(data, model, fitting) never imports this package (an import-linter contract).
"""

from .synth import DISSERTATION_POSTURES, PRESETS, Posture, PresetName, TwinPreset, synthesize

__all__ = ["DISSERTATION_POSTURES", "PRESETS", "Posture", "PresetName", "TwinPreset", "synthesize"]
