"""What both training loops share: a step and its resumable checkpoint, crops that may leave the frame, the photo
as the networks see it.

A run given a checkpoint path writes the whole training state there (model, optimiser, schedule, both random
generators, the losses) every ``checkpoint_every`` steps; started again with it, the run goes on from where it
stopped, bit for bit the run it would have been.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

__all__ = ["Checkpoints", "optimise", "region", "resume", "save_state", "srgb_photo"]


def srgb_photo(x: np.ndarray) -> np.ndarray:
    from bokehray.colour import linear_to_srgb

    return linear_to_srgb(np.clip(x[..., :3], 0.0, 1.0)).astype(np.float32)


@dataclass(frozen=True)
class Checkpoints:
    """A run's checkpoints: the file (None: none are written), how often, and the run they belong to (its length and
    seed: a checkpoint of another run is refused)."""

    path: str | None
    steps: int
    seed: int
    every: int = 500


def optimise(loss, step: int, parts: dict, losses: list[float], rng, checkpoints: Checkpoints) -> None:
    """One training step's end: the optimiser and the schedule of ``parts`` step on ``loss``, which joins
    ``losses``; then the whole state is written when a checkpoint is due (:func:`resume` reads it)."""
    parts["opt"].zero_grad()
    loss.backward()
    parts["opt"].step()
    parts["sched"].step()
    losses.append(loss.item())
    c = checkpoints
    if c.path and ((step + 1) % c.every == 0 or step + 1 == c.steps):
        save_state(c.path, {"steps": c.steps, "seed": c.seed, "step": step + 1, "losses": losses,
                            "rng": rng.bit_generator.state, **{k: v.state_dict() for k, v in parts.items()}})


def region(a: np.ndarray, y0: int, x0: int, size: int, lead: int = 0) -> np.ndarray:
    """The ``size`` x ``size`` window at (``y0``, ``x0``) of ``a``'s spatial axes (after ``lead`` leading axes),
    zeros where it leaves ``a``."""
    h, w = a.shape[lead:lead + 2]
    out = np.zeros(a.shape[:lead] + (size, size) + a.shape[lead + 2:], a.dtype)
    sy, sx, ey, ex = max(y0, 0), max(x0, 0), min(y0 + size, h), min(x0 + size, w)
    pre = (slice(None),) * lead
    out[pre + (slice(sy - y0, ey - y0), slice(sx - x0, ex - x0))] = a[pre + (slice(sy, ey), slice(sx, ex))]
    return out


def save_state(checkpoint: str, state: dict) -> None:
    """Write a training state atomically (a run killed while writing keeps the previous one)."""
    import torch

    tmp = f"{checkpoint}.tmp"
    torch.save({**state, "torch_rng": torch.get_rng_state()}, tmp)
    Path(tmp).replace(checkpoint)


def resume(checkpoints: Checkpoints, parts: dict, rng) -> tuple[list[float], int]:
    """Load the checkpoint (if there is one) into the model, optimiser and schedule of ``parts`` and the generators;
    the losses so far and the step to go on from."""
    import torch

    checkpoint, steps, seed = checkpoints.path, checkpoints.steps, checkpoints.seed
    if not checkpoint or not Path(checkpoint).is_file():
        return [], 0
    state = torch.load(checkpoint, weights_only=False)
    if state["steps"] != steps or state["seed"] != seed:
        raise SystemExit(f"{checkpoint}: a run of {state['steps']} steps with seed {state['seed']}, not {steps} with "
                         f"{seed}: the schedule would differ")
    for key, part in parts.items():
        part.load_state_dict(state[key])
    rng.bit_generator.state = state["rng"]
    torch.set_rng_state(state["torch_rng"])
    print(f"resumed {checkpoint} at step {state['step']}", flush=True)
    return state["losses"], state["step"]
