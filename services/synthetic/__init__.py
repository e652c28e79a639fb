"""Synthetic hand demonstrations with ground truth (objects, hand, motion, camera, generator).

Entry point: :func:`services.synthetic.generator.generate`. Nothing is computed or read at import.
"""

from services.synthetic.generator import (
    EVALUATION_SPLIT,
    OBJECTS,
    TUNING_SPLIT,
    Demonstration,
    GroundTruth,
    JointTruth,
    generate,
    load_npz,
    save_npz,
)

__all__ = [
    "EVALUATION_SPLIT",
    "OBJECTS",
    "TUNING_SPLIT",
    "Demonstration",
    "GroundTruth",
    "JointTruth",
    "generate",
    "load_npz",
    "save_npz",
]
