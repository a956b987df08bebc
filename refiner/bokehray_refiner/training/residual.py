"""``bokehray train-refiner``: train the small one-step refiner on synthetic pairs.

Losses (paper sec. 3.4): MSE and the multi-scale edge loss of eq. 9 in sRGB,
LPIPS when the user points to a local TorchScript LPIPS model, and an optional
adversarial term with a small patch discriminator. AdamW with linear warm-up
and a cosine schedule. The PISA edge hardness rises log-linearly from
``hardness_start`` to ``k_max`` over the first ``hardness_ramp`` of the steps,
then stays (appendix A). Checkpoints hold the model, optimiser, schedule and
the random states (NumPy's batch sampler and torch's CPU generator; nothing random runs on a GPU),
and the configuration includes the corruption shares, so a resumed run continues exactly as an
uninterrupted one.
"""

from __future__ import annotations

import csv
import json
import math
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import torch
import torch.nn as nn
import torch.nn.functional as F
from safetensors.torch import save_file
from tqdm import tqdm

from bokehray.errors import InputError
from bokehray.output.atomic import atomic_write
from bokehray_refiner.masks import PisaMaskProvider
from bokehray_refiner.model import BokehRefiner, RefinerConfig, fingerprint
from bokehray_refiner.pisa import K_MAX, PisaMaskOptions

from .data import CORRUPTION_PROBS, PairBank

__all__ = ["TrainConfig", "edge_loss", "hardness_at", "train"]


@dataclass
class TrainConfig:
    """One training run. ``out`` receives checkpoint.pt, loss.csv, loss.png, refiner.safetensors and refiner.json."""

    data: str
    out: str
    steps: int = 2000
    batch: int = 8
    crop: int = 96
    lr: float = 1e-3
    weight_decay: float = 1e-4
    warmup: int = 100
    variants: int = 2
    corruption_probs: list[float] = field(default_factory=lambda: list(CORRUPTION_PROBS))
    edge_share: float = 0.8
    behind_gate: bool = False
    exact_weight: float = 1.0
    seed: int = 0
    mse_weight: float = 1.0
    edge_weight: float = 0.5
    lpips_weight: float = 0.0
    lpips_model: str | None = None
    adv_weight: float = 0.0
    hardness_start: float = 10.0
    hardness_ramp: float = 0.6
    checkpoint_every: int = 100
    limit: int | None = None
    device: str = "auto"
    model: dict = field(default_factory=lambda: RefinerConfig().as_dict())

    def __post_init__(self) -> None:
        factor = RefinerConfig(**self.model).latent_factor
        if self.steps < 1 or self.batch < 1 or self.checkpoint_every < 1 or self.crop < factor or self.crop % factor:
            raise InputError(f"steps, batch and checkpoint_every must be >= 1 and crop a positive multiple of {factor}")
        if not (math.isfinite(self.exact_weight) and self.exact_weight >= 0):
            raise InputError(f"exact_weight: expected a finite weight >= 0, got {self.exact_weight}")
        if self.lpips_weight > 0 and not self.lpips_model:
            raise InputError("lpips_weight > 0 needs lpips_model: a local TorchScript LPIPS model")


def hardness_at(step: int, cfg: TrainConfig) -> float:
    """Log-linear ramp from ``hardness_start`` to ``k_max``."""
    ramp = max(1.0, cfg.hardness_ramp * cfg.steps)
    t = min(1.0, step / ramp)
    return float(math.exp((1 - t) * math.log(cfg.hardness_start) + t * math.log(K_MAX)))


def _sobel(size: int) -> torch.Tensor:
    """Extended Sobel pair of odd ``size``: binomial smoothing x central difference, unit response to a unit ramp."""
    n = size - 1
    smooth = torch.tensor([math.comb(n, i) for i in range(size)], dtype=torch.float32)
    smooth /= smooth.sum()
    diff = torch.arange(size, dtype=torch.float32) - n / 2
    diff /= (diff * diff).sum()
    gx = smooth[:, None] * diff[None, :]
    return torch.stack([gx, gx.T])[:, None]  # (2, 1, s, s): d/dx, d/dy


def _grad(img: torch.Tensor, kernel: torch.Tensor) -> torch.Tensor:
    b, c, h, w = img.shape
    pad = kernel.shape[-1] // 2
    g = F.conv2d(F.pad(img.reshape(b * c, 1, h, w), (pad,) * 4, mode="replicate"), kernel.to(img))
    return g.view(b, c, 2, h, w)


def edge_loss(pred: torch.Tensor, target: torch.Tensor, focus: torch.Tensor) -> torch.Tensor:
    """Eq. 9: ``sum_l 1/l^2 || (grad_l pred - grad_l target) * max_{I in {target, focus}} |grad_l I| ||_1`` (mean)."""
    total = pred.new_zeros(())
    for level in (1, 2, 3):
        k = _sobel(2 * level + 1)
        gt, gf = _grad(target, k), _grad(focus, k)
        weight = torch.maximum(gt.norm(dim=2, keepdim=True), gf.norm(dim=2, keepdim=True)).detach()
        total = total + ((_grad(pred, k) - gt).abs() * weight).mean() / level**2
    return total


class _PatchDiscriminator(nn.Module):
    def __init__(self, ch: int = 32):
        super().__init__()
        self.net = nn.Sequential(
            nn.Conv2d(6, ch, 4, 2, 1), nn.LeakyReLU(0.2),
            nn.Conv2d(ch, 2 * ch, 4, 2, 1), nn.GroupNorm(8, 2 * ch), nn.LeakyReLU(0.2),
            nn.Conv2d(2 * ch, 1, 3, 1, 1))

    def forward(self, image: torch.Tensor, focus: torch.Tensor) -> torch.Tensor:
        return self.net(torch.cat([image, focus], 1))


def _device(name: str) -> torch.device:
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    return torch.device(name)


def _lr_lambda(cfg: TrainConfig):
    def f(step: int) -> float:
        if step < cfg.warmup:
            return (step + 1) / cfg.warmup
        t = (step - cfg.warmup) / max(1, cfg.steps - cfg.warmup)
        return 0.5 * (1.0 + math.cos(math.pi * min(1.0, t)))
    return f


def _to_tensors(batch: dict, device) -> tuple[torch.Tensor, ...]:
    img = lambda a: torch.from_numpy(a).permute(0, 3, 1, 2).to(device)  # noqa: E731
    coc = batch["k_px"][:, None, None] * (batch["disparity"] - batch["focus_disparity"][:, None, None])
    return img(batch["focus"]), img(batch["render"]), img(batch["target"]), torch.from_numpy(coc).to(device)


def _save_plot(rows: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    steps = np.array([r["step"] for r in rows])
    fig, ax = plt.subplots(figsize=(6, 3.5), dpi=120)
    for key in ("loss", "mse", "edge"):
        vals = np.array([r[key] for r in rows])
        k = max(1, len(vals) // 50)
        smooth = np.convolve(vals, np.ones(k) / k, mode="valid")
        ax.plot(steps[k - 1:], smooth, label=key)
    ax.set_yscale("log")
    ax.set_xlabel("step")
    ax.set_ylabel("training loss (running mean)")
    ax.legend()
    ax.grid(alpha=0.3)
    fig.tight_layout()
    atomic_write(path, fig.savefig)
    plt.close(fig)


def _write_csv(rows: list[dict], tmp: str) -> None:
    with open(tmp, "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(rows[-1]))
        writer.writeheader()
        writer.writerows(rows)


def export_weights(model: BokehRefiner, path: Path, meta: dict) -> None:
    """Write ``refiner.safetensors`` (weights) and ``refiner.json`` (architecture and provenance) atomically."""
    state = {k: v.detach().cpu().contiguous() for k, v in model.state_dict().items()}
    atomic_write(path, lambda tmp: save_file(state, tmp, metadata={"config": json.dumps(model.config.as_dict())}))
    atomic_write(path.with_suffix(".json"), lambda tmp: Path(tmp).write_text(json.dumps(meta, indent=2)))


@dataclass
class _Run:
    """One training run's state: what a checkpoint holds, and where it goes."""

    cfg: TrainConfig
    out: Path
    device: torch.device
    model: BokehRefiner
    opt: torch.optim.Optimizer
    sched: torch.optim.lr_scheduler.LRScheduler
    rng: np.random.Generator
    disc: nn.Module | None = None
    d_opt: torch.optim.Optimizer | None = None
    lpips: torch.nn.Module | None = None
    step: int = 0
    rows: list = field(default_factory=list)

    @property
    def checkpoint(self) -> Path:
        return self.out / "checkpoint.pt"


def _new_run(cfg: TrainConfig, out: Path) -> _Run:
    """A fresh run: seeded model, optimiser, schedule, the optional discriminator and LPIPS, the crop generator."""
    device = _device(cfg.device)
    torch.manual_seed(cfg.seed)
    model = BokehRefiner(RefinerConfig(**cfg.model)).to(device)
    opt = torch.optim.AdamW(model.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)
    sched = torch.optim.lr_scheduler.LambdaLR(opt, _lr_lambda(cfg))
    run = _Run(cfg, out, device, model, opt, sched, rng=None)
    if cfg.adv_weight > 0:
        run.disc = _PatchDiscriminator().to(device)
        run.d_opt = torch.optim.AdamW(run.disc.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)
    run.lpips = torch.jit.load(cfg.lpips_model, map_location=device).eval() if cfg.lpips_weight > 0 else None
    run.rng = np.random.default_rng(cfg.seed)
    return run


def _resume(run: _Run, stop_at: int | None) -> None:
    """Load the run's checkpoint into it (written by the same configuration, at or before ``stop_at``)."""
    ckpt = run.checkpoint
    state = torch.load(ckpt, map_location=run.device, weights_only=False)
    if state["config"] != asdict(run.cfg):
        raise InputError(f"{ckpt}: written by a different configuration; use a new --out or --no-resume")
    run.model.load_state_dict(state["model"])
    run.opt.load_state_dict(state["opt"])
    run.sched.load_state_dict(state["sched"])
    if run.disc is not None:
        run.disc.load_state_dict(state["disc"])
        run.d_opt.load_state_dict(state["d_opt"])
    run.rng.bit_generator.state = state["rng"]
    torch.set_rng_state(state["torch_rng"])
    run.step, run.rows = state["step"], state["rows"]
    if stop_at is not None and run.step > stop_at:
        raise InputError(f"{ckpt}: the checkpoint is at step {run.step}, past --stop-at {stop_at}")


def _losses(run: _Run, batch: dict) -> tuple[torch.Tensor, dict, float, torch.Tensor,
                                            tuple[torch.Tensor, torch.Tensor]]:
    """The step's loss on ``batch`` and its parts; also the PISA hardness, the prediction and the focus image."""
    cfg, device = run.cfg, run.device
    focus, render, target, coc = _to_tensors(batch, device)
    opts = PisaMaskOptions(hardness=hardness_at(run.step, cfg))
    pisa = PisaMaskProvider(batch["disparity"], batch["focus_disparity"], batch["k_px"], opts, torch_device=device)
    # what refine keeps: the network's output within the edge band (times the gate, with behind_gate), the
    # classical render elsewhere
    band = torch.from_numpy(batch["band"])[:, None].to(device)
    pred = render + band * (run.model(focus, render, coc, pisa) - render)
    inside = (band > 0).to(pred.dtype)  # the MSE over the band only: outside it the error is not the model's
    if cfg.exact_weight != 1.0:  # a change to a render of the exact map is harm: weighted up (or down)
        exact = torch.from_numpy(batch["exact"]).to(device)
        inside = inside * torch.where(exact, cfg.exact_weight, 1.0).to(pred.dtype)[:, None, None, None]
    parts = {"mse": ((pred - target) ** 2 * inside).sum() / (3 * inside.sum()).clamp(min=1.0),
             "edge": edge_loss(pred, target, focus)}
    loss = cfg.mse_weight * parts["mse"] + cfg.edge_weight * parts["edge"]
    if run.lpips is not None:
        parts["lpips"] = run.lpips(pred.clamp(0, 1) * 2 - 1, target * 2 - 1).mean()
        loss = loss + cfg.lpips_weight * parts["lpips"]
    if run.disc is not None:
        parts["adv"] = F.softplus(-run.disc(pred, focus)).mean()  # -log D(pred)
        loss = loss + cfg.adv_weight * parts["adv"]
    return loss, parts, opts.hardness, pred, (focus, target)


def _step(run: _Run, bank: PairBank) -> None:
    """One optimiser step (and the discriminator's), its row appended to the run's."""
    cfg = run.cfg
    t0 = time.perf_counter()
    batch = bank.batch(run.rng, cfg.batch, cfg.crop, edge_share=cfg.edge_share)
    loss, parts, hardness, pred, (focus, target) = _losses(run, batch)
    run.opt.zero_grad(set_to_none=True)
    loss.backward()
    torch.nn.utils.clip_grad_norm_(run.model.parameters(), 1.0)
    run.opt.step()
    run.sched.step()
    if run.disc is not None:  # L_D = -log D(target) - log(1 - D(pred))
        d_loss = F.softplus(-run.disc(target, focus)).mean() + F.softplus(run.disc(pred.detach(), focus)).mean()
        run.d_opt.zero_grad(set_to_none=True)
        d_loss.backward()
        run.d_opt.step()
    run.step += 1
    run.rows.append({"step": run.step, "loss": loss.item(), "mse": parts["mse"].item(), "edge": parts["edge"].item(),
                     "lr": run.sched.get_last_lr()[0], "hardness": hardness, "sec": time.perf_counter() - t0}
                    | {k: v.item() for k, v in parts.items() if k in ("lpips", "adv")})


def _save_checkpoint(run: _Run) -> None:
    """The whole state, the loss table and its plot, each written atomically."""
    state = {"model": run.model.state_dict(), "opt": run.opt.state_dict(), "sched": run.sched.state_dict(),
             "rng": run.rng.bit_generator.state, "torch_rng": torch.get_rng_state(), "step": run.step,
             "rows": run.rows, "config": asdict(run.cfg)}
    if run.disc is not None:
        state |= {"disc": run.disc.state_dict(), "d_opt": run.d_opt.state_dict()}
    atomic_write(run.checkpoint, lambda tmp: torch.save(state, tmp))
    atomic_write(run.out / "loss.csv", lambda tmp: _write_csv(run.rows, tmp))
    _save_plot(run.rows, run.out / "loss.png")


def train(cfg: TrainConfig, resume: bool = True, progress: bool = True, bank: PairBank | None = None,
          stop_at: int | None = None) -> Path | None:
    """Run (or resume) a training run; returns the path of the exported weights.

    ``stop_at`` ends the run at that step (or at once, if a resumed checkpoint is already past it), writes a
    checkpoint and exports the weights of that step: ``train --steps N --stop-at M`` reproduces a run of N steps
    that was stopped at step M (resuming needs a checkpoint at or before M).
    """
    if stop_at is not None and stop_at < 1:
        raise InputError(f"stop_at: expected >= 1, got {stop_at}")
    out = Path(cfg.out)
    out.mkdir(parents=True, exist_ok=True)
    run = _new_run(cfg, out)
    if resume and run.checkpoint.is_file():
        _resume(run, stop_at)
    if bank is None:  # kept in the run folder: a resumed run reads it instead of rendering it again
        bank = PairBank.cached(out / "bank.npz", cfg.data, progress=progress, variants=cfg.variants, seed=cfg.seed,
                               limit=cfg.limit, probs=tuple(cfg.corruption_probs), gated=cfg.behind_gate)
    run.model.train()
    bar = tqdm(total=cfg.steps, initial=run.step, desc="training refiner", disable=not progress, unit="step")
    while run.step < cfg.steps and (stop_at is None or run.step < stop_at):
        _step(run, bank)
        bar.update(1)
        bar.set_postfix(loss=f"{run.rows[-1]['loss']:.4g}")
        if run.step % cfg.checkpoint_every == 0 or run.step == cfg.steps or run.step == stop_at:
            _save_checkpoint(run)
        if stop_at is not None and run.step >= stop_at:
            break
    bar.close()
    weights = out / "refiner.safetensors"
    rows = run.rows
    export_weights(run.model, weights, {"model": run.model.config.as_dict(), "train": asdict(cfg), "steps": run.step,
                                        "fingerprint": fingerprint(run.model), "stopped_at": stop_at,
                                        "final_loss": rows[-1]["loss"] if rows else None,
                                        "train_seconds": float(sum(r["sec"] for r in rows))})
    return weights
