"""RLSAC: reinforcement-learning enhanced sample consensus (Nie et al., ICCV 2023)."""

__version__ = "0.1.0"
