"""Bai 2022 Fig. 5 (section III-C): the dueling deep Q network (torch).

  o_z (3 x 180) -> Conv1d 32 filters, kernel 5, stride 2, ReLU -> Conv1d 32, kernel 3, stride 2, ReLU
               -> FC 32, ReLU
  o_r (n x 2, farthest first) -> LSTM, 16 outputs (its last hidden state; zeros when n = 0)
  [FC 32, LSTM 16, o_g (2), o_v (2)] -> FC 128, ReLU -> V (1) and A (15), linear
  Q = V + A - mean(A)                                   (dueling combination, Wang et al. [29])

A batch carries its neighbours right-padded to the longest sequence with their counts; the LSTM
is causal, so its output at step n-1 of a padded row is exactly that of the unpadded sequence.
"""

from __future__ import annotations

import torch
from torch import nn

from .observation import BEAMS, N_ACTIONS, N_SCANS


class DuelingQNet(nn.Module):
    def __init__(self, beams: int = BEAMS, n_scans: int = N_SCANS, n_actions: int = N_ACTIONS, lstm: int = 16):
        super().__init__()
        self.conv = nn.Sequential(nn.Conv1d(n_scans, 32, 5, stride=2), nn.ReLU(), nn.Conv1d(32, 32, 3, stride=2), nn.ReLU())
        n_conv = 32 * (((beams - 5) // 2 + 1 - 3) // 2 + 1)
        self.fc_scan = nn.Sequential(nn.Flatten(), nn.Linear(n_conv, 32), nn.ReLU())
        self.lstm = nn.LSTM(2, lstm, batch_first=True)
        self.fc = nn.Sequential(nn.Linear(32 + lstm + 4, 128), nn.ReLU())
        self.value = nn.Linear(128, 1)
        self.advantage = nn.Linear(128, n_actions)
        self.lstm_size = lstm

    def forward(self, scans: torch.Tensor, goal_vel: torch.Tensor, nb: torch.Tensor | None = None,
                n_nb: torch.Tensor | None = None) -> torch.Tensor:
        """scans (B, 3, 180), goal_vel (B, 4) = [o_g, o_v], nb (B, T, 2) = o_r right-padded, n_nb (B,) counts -> Q (B, 15)."""
        z = self.fc_scan(self.conv(scans))
        B = scans.shape[0]
        if nb is None or nb.shape[1] == 0:
            h = z.new_zeros(B, self.lstm_size)
        else:
            out, _ = self.lstm(nb)
            if n_nb is None:
                h = out[:, -1]
            else:
                n = n_nb.long()
                idx = (n - 1).clamp(min=0)
                h = out[torch.arange(B), idx] * (n > 0).unsqueeze(1).to(out.dtype)
        x = self.fc(torch.cat([z, h, goal_vel], dim=1))
        a = self.advantage(x)
        return self.value(x) + a - a.mean(dim=1, keepdim=True)
