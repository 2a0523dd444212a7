"""RLSAC: reinforcement-learning enhanced sample consensus (Nie et al., ICCV 2023)."""

from rlsac import numerics as _numerics

# before anything of ours imports torch, numpy or OpenCV: their code paths are chosen when they load
_numerics.apply_pins()

__version__ = "0.1.0"
