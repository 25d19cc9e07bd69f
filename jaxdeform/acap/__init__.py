"""The ACAP representation (Gao et al. 2019) and its temporal variant TS-ACAP (seed 002).

Public API: :func:`encode`, :func:`decode`, :class:`Scaler`, :func:`prepare` (an :class:`Acap` to reuse
for many calls on one reference).
"""

from jaxdeform.acap.features import (
    Acap,
    Scaler,
    align_turns,
    cached,
    decode,
    default_solver,
    encode,
    features_from,
    gradients_from_features,
    prepare,
    split_features,
    turn_reference,
)
from jaxdeform.acap.reconstruct import SOLVERS, SolveInfo

__all__ = [
    "SOLVERS",
    "Acap",
    "Scaler",
    "SolveInfo",
    "align_turns",
    "cached",
    "decode",
    "default_solver",
    "encode",
    "features_from",
    "gradients_from_features",
    "prepare",
    "split_features",
    "turn_reference",
]
