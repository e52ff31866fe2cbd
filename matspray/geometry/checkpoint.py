"""Training checkpoints, written atomically, so an interrupted geometry run resumes where it stopped."""

from __future__ import annotations

from pathlib import Path

import torch

from matspray.data.images import save_torch_atomic
from matspray.errors import RunError, file_error
from matspray.geometry.config import ADDED_LATER, GeometryConfig

CHECKPOINT_VERSION = 1


def save_checkpoint(path, config: GeometryConfig, iteration: int, state: dict) -> None:
    """`state`: tensors and plain values (optimizer, density statistics, random generator...)."""
    save_torch_atomic(
        {"version": CHECKPOINT_VERSION, "config": config.identity(), "iteration": iteration, "state": state}, path
    )


def load_checkpoint(path, config: GeometryConfig) -> tuple[int, dict] | None:
    """(iteration, state) of the checkpoint at `path`, None when there is none. A checkpoint made with
    other settings is refused: resuming it would mix two runs."""
    path = Path(path)
    if not path.exists():
        return None
    try:
        data = torch.load(path, map_location="cpu", weights_only=False)
    except Exception as exc:  # a truncated or foreign file
        raise file_error(
            path,
            f"is not a readable checkpoint ({type(exc).__name__}: {exc})",
            "delete it, or restart the geometry stage",
        ) from None
    if not isinstance(data, dict) or data.get("version") != CHECKPOINT_VERSION:
        raise file_error(
            path, "is not a matspray geometry checkpoint of this version", "delete it, or restart the geometry stage"
        )
    saved = {**ADDED_LATER, **data["config"]}
    differences = sorted(k for k, v in config.to_dict().items() if saved.get(k) != v)
    if differences:
        shown = ", ".join(f"{k}: {saved.get(k)!r} -> {getattr(config, k)!r}" for k in differences[:4])
        raise RunError(
            f"{path}: was made with other geometry settings ({shown}); "
            "use another run folder, or restart the geometry stage to discard the earlier training"
        )
    return int(data["iteration"]), data["state"]
