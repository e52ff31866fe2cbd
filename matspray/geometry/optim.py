"""Adam over the Gaussians' parameter tensors, one group per tensor, that survives densification:
rows can be kept, dropped and appended together with their Adam moments."""

from __future__ import annotations

import math

import torch
from torch import Tensor

from matspray.gaussians import Gaussians

PARAMETERS = ("means", "log_scales", "quats", "opacity_logits", "sh_dc", "sh_rest")


def split_sh(gaussians: Gaussians) -> dict[str, Tensor]:
    """The trainable tensors: SH DC and the higher bands get separate learning rates."""
    return {
        "means": gaussians.means,
        "log_scales": gaussians.log_scales,
        "quats": gaussians.quats,
        "opacity_logits": gaussians.opacity_logits,
        "sh_dc": gaussians.sh[:, :1],
        "sh_rest": gaussians.sh[:, 1:],
    }


class GaussianOptimizer:
    """Adam (3DGS settings: eps 1e-15) on leaf tensors named as in PARAMETERS."""

    def __init__(self, gaussians: Gaussians, lrs: dict[str, float]):
        self.params = {name: t.detach().clone().requires_grad_(True) for name, t in split_sh(gaussians).items()}
        # fused: one kernel for all six tensors (torch's default on the CPU is a loop of small operations per tensor);
        # the same update to rounding
        self.adam = torch.optim.Adam(
            [{"params": [self.params[name]], "lr": lrs[name], "name": name} for name in PARAMETERS],
            eps=1e-15,
            fused=True,
        )

    def gaussians(self) -> Gaussians:
        """The current Gaussians, differentiable w.r.t. the optimised tensors."""
        p = self.params
        return Gaussians(
            p["means"], p["log_scales"], p["quats"], p["opacity_logits"], torch.cat([p["sh_dc"], p["sh_rest"]], dim=1)
        )

    def set_lr(self, name: str, lr: float) -> None:
        for group in self.adam.param_groups:
            if group["name"] == name:
                group["lr"] = lr

    def step(self) -> None:
        self.adam.step()
        self.adam.zero_grad(set_to_none=True)

    def edit(self, keep: Tensor, appended: Gaussians | None = None) -> None:
        """Keep the rows `keep` (bool [N] or indices) and append new Gaussians, whose Adam moments
        start at zero."""
        new_rows = split_sh(appended) if appended is not None else None
        for group in self.adam.param_groups:
            name = group["name"]
            old = group["params"][0]
            rows = old.detach()[keep]
            if new_rows is not None:
                rows = torch.cat([rows, new_rows[name].detach().to(rows)])
            param = rows.clone().requires_grad_(True)
            state = self.adam.state.pop(old, None)
            if state:
                for key in ("exp_avg", "exp_avg_sq"):
                    kept = state[key][keep]
                    if new_rows is not None:
                        kept = torch.cat([kept, torch.zeros_like(new_rows[name]).to(kept)])
                    state[key] = kept
                self.adam.state[param] = state
            group["params"][0] = param
            self.params[name] = param

    def replace_values(self, name: str, values: Tensor, reset_moments: bool = True) -> None:
        """Overwrite one tensor (e.g. an opacity reset), optionally zeroing its Adam moments."""
        param = self.params[name]
        with torch.no_grad():
            param.copy_(values)
        state = self.adam.state.get(param)
        if reset_moments and state:
            state["exp_avg"].zero_()
            state["exp_avg_sq"].zero_()

    def state_dict(self) -> dict:
        return {"params": {k: v.detach().clone() for k, v in self.params.items()}, "adam": self.adam.state_dict()}

    def load_state_dict(self, state: dict) -> None:
        for group in self.adam.param_groups:
            name = group["name"]
            param = state["params"][name].clone().requires_grad_(True)
            group["params"][0] = param
            self.params[name] = param
        self.adam.load_state_dict(state["adam"])


def exponential_lr(step: int, total: int, start: float, end: float) -> float:
    """Log-linear interpolation from `start` at step 0 to `end` at step `total` (3DGS position schedule)."""
    t = min(max(step / max(total, 1), 0.0), 1.0)
    return math.exp((1 - t) * math.log(start) + t * math.log(end))
