"""The RL environment's state encoding (rlsac.rl.env): what the policy sees of a row, its instance's data features and
three memory features (action, residual, history), and how a step's chosen set updates them.

Part of ``SampleConsensusEnv`` (a mixin): it owns ``data`` (R, N, c) and ``action``, ``residual``, ``history``
(R, N); it reads the rows' ``mask``, the ``conf`` (``residual_clip``) and the ``state_threshold``.
"""

from __future__ import annotations

import torch

MEMORY_DIM = 3  # the memory features appended to the data features: action, residual, history


class StateEncoding:
    """The state of every row: data features and memory (``reset`` starts it, ``step`` updates it)."""

    def _start_state(self, features: torch.Tensor) -> None:
        """The first state's features: the instances' data features per row, no set chosen yet."""
        R, N, dev = self.B * self.E, self.N, self.coords.device
        self.data = features.repeat_interleave(self.E, 0)
        self.history = torch.zeros((R, N), device=dev)
        self.action = torch.full((R, N), -1.0, device=dev)
        self.residual = torch.ones((R, N), device=dev)

    def state(self) -> torch.Tensor:
        return torch.cat([self.data, self.memory()], dim=-1)

    def memory(self) -> torch.Tensor:
        """(R, N, 3): action, residual, history."""
        return torch.stack([self.action, self.residual, self.history], dim=-1)

    def _update_memory(self, idx: torch.Tensor, res: torch.Tensor, act: torch.Tensor) -> None:
        """The memory features of the next state; only rows that acted change."""
        conf = self.conf
        onehot = torch.zeros_like(self.action, dtype=torch.bool).scatter_(1, idx, True)
        a = act[:, None]
        self.action = torch.where(a, onehot.float() * 2 - 1, self.action)
        r_feat = (res / self.state_threshold).clamp(max=conf.residual_clip) / conf.residual_clip
        self.residual = torch.where(a, r_feat.masked_fill(~self.mask, 1.0), self.residual)
        self.history = self.history + (onehot & a).float()
