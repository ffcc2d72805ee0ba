"""Train the prior (encoder + decoder) on procedural patches.

``python -m mapping.training.train [--config configs/train_prior.yaml] [--out DIR] [--steps N]
[--device auto|cpu|cuda] [--resume] [--export PATH]``

Conditional-neural-process style (docs/design.md §3.4): per patch, the encoder sees the noisy
observed surface points with normals and its latent is their mean; the decoder predicts (mean,
sigma) of the SDF at the patch's samples; the loss is the Gaussian negative log-likelihood of the
SDF clamped to ``+-sdf_clamp_vu`` plus a small penalty on the latent norm. Adam with a cosine
learning rate, atomic checkpoints every ``checkpoint_every`` steps (resumable with ``--resume``),
and at the end ``prior.pt`` (loadable with :meth:`mapping.networks.PriorModel.load`) with the
held-out metric in its metadata.
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime as _dt
import io
import json
import logging
import math
import os
import platform
import sys
import time
from pathlib import Path

import torch
from pydantic import BaseModel, ConfigDict, Field

from common.atomic_io import write_bytes_atomic
from mapping.config import resolve_device
from mapping.networks import ModelConfig, PriorModel
from mapping.training.patches import (
    PatchBatch,
    PatchConfig,
    generate_patches,
    generate_patches_with_scenes,
)
from mapping.training.scenes import Scenes

log = logging.getLogger(__name__)

EVAL_SEED_BASE = 1_000_000_000  # held-out patches use seeds from here; training seeds stay below


class TrainConfig(BaseModel):
    """Training of the prior. Lengths are in voxel units (vu)."""

    model_config = ConfigDict(extra="forbid")

    seed: int = Field(0, ge=0, description="Seed of the model initialisation and the patch stream.")
    steps: int = Field(1000, ge=1, description="Optimisation steps.")
    batch_size: int = Field(64, ge=1, description="Patches per step.")
    lr: float = Field(2e-3, gt=0, description="Peak learning rate of Adam.")
    lr_final: float = Field(2e-5, ge=0, description="Learning rate at the end of the cosine decay.")
    warmup_steps: int = Field(50, ge=0, description="Linear warm-up steps before the cosine decay.")
    grad_clip: float = Field(1.0, gt=0, description="Clip the global gradient norm to this.")
    sdf_clamp_vu: float = Field(
        0.5,
        gt=0,
        description="Targets are clamped to +-this. Must cover a meshing lattice step (0.25 vu) "
        "with margin, so that marching cubes interpolates between unclamped values.",
    )
    latent_penalty: float = Field(
        1e-3, ge=0, description="Weight of the mean squared latent entry added to the loss."
    )
    nll_beta: float = Field(
        0.0,
        ge=0,
        le=1,
        description="beta-NLL (Seitzer et al. 2022): each sample's NLL is weighted by the "
        "detached sigma^(2 beta); 0 is the plain Gaussian NLL, 0.5 keeps the mean fitting where "
        "the model is uncertain.",
    )
    threads: int = Field(
        1,
        ge=1,
        description="torch.set_num_threads on CPU (1 measured ~4x faster than 2 on a loaded "
        "2-core machine: the tensors are small).",
    )
    checkpoint_every: int = Field(250, ge=1, description="Checkpoint every this many steps.")
    log_every: int = Field(25, ge=1, description="Log the running loss every this many steps.")
    eval_patches: int = Field(256, ge=1, description="Held-out patches for the final metric.")
    eval_near_vu: float = Field(
        0.1, gt=0, description="Held-out metric: mean |SDF error| over samples with |SDF| < this."
    )
    model: dict = Field(
        default_factory=dict, description="Overrides of mapping.networks.ModelConfig defaults."
    )
    patches: PatchConfig = Field(
        default_factory=lambda: PatchConfig(
            n_queries=1024, shell_candidates=3072, surface_pool=256
        ),
        description="Training patch generator (n_queries per patch; see mapping.training.patches).",
    )


# ---------------------------------------------------------------------------------------------
# Loss and metric
# ---------------------------------------------------------------------------------------------


def encode_patches(model: PriorModel, batch: PatchBatch) -> torch.Tensor:
    """Latent of each patch: mean of the per-point codes over its valid points, ``(B, C, 3)``."""
    codes = model.encoder(batch.points, batch.normals)  # (B, N, C, 3)
    w = batch.point_mask.to(codes.dtype)[..., None, None]
    return (codes * w).sum(1) / w.sum(1).clamp_min(1.0)


def patch_loss(
    model: PriorModel,
    batch: PatchBatch,
    sdf_clamp_vu: float,
    latent_penalty: float,
    nll_beta: float = 0.0,
) -> tuple[torch.Tensor, dict[str, float]]:
    """Gaussian (beta-)NLL of the clamped SDF under (mean, sigma) + latent penalty; its parts."""
    F = encode_patches(model, batch)
    mean, sigma = model.decoder(F, batch.queries)
    target = batch.sdf.clamp(-sdf_clamp_vu, sdf_clamp_vu)
    nll = torch.log(sigma) + 0.5 * ((mean - target) / sigma) ** 2
    if nll_beta > 0:
        nll = nll * sigma.detach() ** (2 * nll_beta)
    mask = (batch.sdf_mask & batch.point_mask.any(-1, keepdim=True)).to(nll.dtype)
    nll = (nll * mask).sum() / mask.sum().clamp_min(1.0)
    penalty = (F * F).mean()
    loss = nll + latent_penalty * penalty
    with torch.no_grad():
        mae = ((mean - target).abs() * mask).sum() / mask.sum().clamp_min(1.0)
    return loss, {"loss": loss.item(), "nll": nll.item(), "mae_vu": mae.item()}


def heldout_sets(n_patches: int, chunk: int = 64) -> list[tuple[PatchBatch, Scenes]]:
    """The fixed-seed held-out set (generator defaults: 4096 SDF samples per patch), in batches
    of ``chunk`` patches, each with the scenes it was cut from (for exact SDF)."""
    sizes = [min(chunk, n_patches - i) for i in range(0, n_patches, chunk)]
    return [generate_patches_with_scenes(n, EVAL_SEED_BASE + i) for i, n in enumerate(sizes)]


def heldout_batches(n_patches: int) -> list[PatchBatch]:
    """:func:`heldout_sets` without the scenes."""
    return [batch for batch, _ in heldout_sets(n_patches)]


@torch.no_grad()
def evaluate(
    model: PriorModel, batches: list[PatchBatch], near_vu: float = 0.1, sdf_clamp_vu: float = 0.5
) -> dict[str, float]:
    """Held-out metrics: mean |SDF error| near the surface (|SDF| < near_vu), within the clamp,
    sign accuracy within the clamp, and the mean predicted sigma near the surface (all in vu)."""
    device = next(model.parameters()).device
    sums = {"near_err": 0.0, "near_n": 0.0, "clamp_err": 0.0, "clamp_n": 0.0, "sign_ok": 0.0}
    sums["near_sigma"] = 0.0
    for batch in batches:
        batch = batch.to(device)
        F = encode_patches(model, batch)
        mean, sigma = model.decoder(F, batch.queries)
        valid = batch.sdf_mask & batch.point_mask.any(-1, keepdim=True)
        near = valid & (batch.sdf.abs() < near_vu)
        within = valid & (batch.sdf.abs() < sdf_clamp_vu)
        err = (mean - batch.sdf).abs()
        sums["near_err"] += err[near].sum().item()
        sums["near_sigma"] += sigma[near].sum().item()
        sums["near_n"] += near.sum().item()
        sums["clamp_err"] += err[within].sum().item()
        sums["clamp_n"] += within.sum().item()
        sums["sign_ok"] += ((mean > 0) == (batch.sdf > 0))[within].sum().item()
    return {
        "mae_near_vu": sums["near_err"] / max(sums["near_n"], 1.0),
        "sigma_near_vu": sums["near_sigma"] / max(sums["near_n"], 1.0),
        "mae_clamp_vu": sums["clamp_err"] / max(sums["clamp_n"], 1.0),
        "sign_accuracy": sums["sign_ok"] / max(sums["clamp_n"], 1.0),
    }


# ---------------------------------------------------------------------------------------------
# Training loop
# ---------------------------------------------------------------------------------------------


def learning_rate(cfg: TrainConfig, step: int) -> float:
    if step < cfg.warmup_steps:
        return cfg.lr * (step + 1) / cfg.warmup_steps
    span = max(cfg.steps - cfg.warmup_steps, 1)
    progress = min((step - cfg.warmup_steps) / span, 1.0)
    return cfg.lr_final + 0.5 * (cfg.lr - cfg.lr_final) * (1.0 + math.cos(math.pi * progress))


def _atomic_torch_save(payload: dict, path: Path) -> None:
    buffer = io.BytesIO()
    torch.save(payload, buffer)
    write_bytes_atomic(path, buffer.getvalue())


def _resumable(config: dict) -> dict:
    """The part of a training config a resumed run must share with its checkpoint."""
    return {k: v for k, v in config.items() if k != "steps"}


def machine_description(device: torch.device) -> str:
    if device.type == "cuda":
        return f"{torch.cuda.get_device_name(device)} (CUDA), {platform.machine()}"
    return (
        f"{platform.processor() or platform.machine()}, {os.cpu_count()} logical CPUs, "
        f"torch threads {torch.get_num_threads()}"
    )


def train(
    cfg: TrainConfig,
    out_dir: Path,
    device: torch.device | None = None,
    resume: bool = False,
    show_progress: bool = True,
    command: str = "",
) -> tuple[PriorModel, dict]:
    """Run the training; returns the model and the metadata written into ``out_dir/prior.pt``."""
    from tqdm import tqdm

    device = device or torch.device("cpu")
    if device.type == "cpu":
        torch.set_num_threads(cfg.threads)
    out_dir.mkdir(parents=True, exist_ok=True)
    torch.manual_seed(cfg.seed)
    model = PriorModel(ModelConfig(**cfg.model)).to(device)
    opt = torch.optim.Adam(model.parameters(), lr=cfg.lr)
    ckpt_path = out_dir / "checkpoint.pt"
    start, elapsed, history = 0, 0.0, []
    if resume and ckpt_path.is_file():
        ckpt = torch.load(ckpt_path, map_location=device, weights_only=True)
        if _resumable(ckpt["train_config"]) != _resumable(cfg.model_dump(mode="json")):
            raise SystemExit(
                f"{ckpt_path}: written with another training config; use the same config "
                "(only --steps may change) or drop --resume / choose another --out"
            )
        model.load_state_dict(ckpt["model"])
        opt.load_state_dict(ckpt["optimizer"])
        start, elapsed, history = ckpt["step"], ckpt["elapsed_s"], list(ckpt["history"])
        log.info("resumed from %s at step %d", ckpt_path, start)

    def checkpoint(step: int) -> None:
        _atomic_torch_save(
            {
                "step": step,
                "elapsed_s": elapsed,
                "history": history,
                "model": model.state_dict(),
                "optimizer": opt.state_dict(),
                "train_config": cfg.model_dump(mode="json"),
            },
            ckpt_path,
        )

    model.train()
    bar = tqdm(range(start, cfg.steps), initial=start, total=cfg.steps, disable=not show_progress)
    running: list[float] = []
    for step in bar:
        t0 = time.perf_counter()
        batch = generate_patches(cfg.batch_size, cfg.seed * 1_000_003 + step, cfg.patches)
        batch = batch.to(device)
        for group in opt.param_groups:
            group["lr"] = learning_rate(cfg, step)
        loss, parts = patch_loss(model, batch, cfg.sdf_clamp_vu, cfg.latent_penalty, cfg.nll_beta)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(model.parameters(), cfg.grad_clip)
        opt.step()
        elapsed += time.perf_counter() - t0
        running.append(parts["loss"])
        if (step + 1) % cfg.log_every == 0 or step + 1 == cfg.steps:
            mean_loss = sum(running) / len(running)
            history.append([step + 1, mean_loss, parts["mae_vu"], elapsed])
            log.info(
                "step %d loss %.4f mae %.4f vu lr %.2e elapsed %.0f s",
                step + 1,
                mean_loss,
                parts["mae_vu"],
                learning_rate(cfg, step),
                elapsed,
            )
            running = []
        bar.set_postfix(loss=f"{parts['loss']:.3f}", mae=f"{parts['mae_vu']:.3f}")
        if (step + 1) % cfg.checkpoint_every == 0 and step + 1 < cfg.steps:
            checkpoint(step + 1)
    checkpoint(cfg.steps)

    model.eval()
    batches = heldout_batches(cfg.eval_patches)
    metrics = evaluate(model, batches, cfg.eval_near_vu, cfg.sdf_clamp_vu)
    quick = evaluate(model, batches[:1], cfg.eval_near_vu, cfg.sdf_clamp_vu)
    final_losses = [h[1] for h in history[-4:]]
    metadata = {
        "steps": cfg.steps,
        "train_wall_s": round(elapsed, 1),
        "final_loss": sum(final_losses) / max(len(final_losses), 1),
        "heldout": {
            **metrics,
            "eval_patches": cfg.eval_patches,
            "eval_seed_base": EVAL_SEED_BASE,
            "near_vu": cfg.eval_near_vu,
        },
        "heldout_quick": {
            **quick,
            "eval_patches": batches[0].points.shape[0],
            "eval_seed_base": EVAL_SEED_BASE,
            "near_vu": cfg.eval_near_vu,
        },
        "sdf_clamp_vu": cfg.sdf_clamp_vu,
        "train_config": cfg.model_dump(mode="json"),
        "model_config": dataclasses.asdict(model.cfg),
        "command": command,
        "date": _dt.datetime.now().astimezone().isoformat(timespec="seconds"),
        "machine": machine_description(device),
        "torch": str(torch.__version__),
    }
    metadata = json.loads(json.dumps(metadata))  # plain types only: loadable with weights_only
    model = model.cpu()
    model.save(out_dir / "prior.pt", metadata)
    log.info("held-out %s", metrics)
    return model, metadata


def load_config(path: Path | None) -> TrainConfig:
    if path is None:
        return TrainConfig()
    import yaml

    if not path.is_file():
        raise SystemExit(f"{path}: config file not found")
    try:
        data = yaml.safe_load(path.read_text()) or {}
        return TrainConfig(**data)
    except Exception as exc:
        first = str(exc).splitlines()[0] if str(exc) else exc.__class__.__name__
        raise SystemExit(f"{path}: invalid training config ({first}); fix the YAML") from None


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(
        prog="python -m mapping.training.train", description=__doc__.split("\n")[0]
    )
    parser.add_argument("--config", type=Path, default=None, help="YAML with TrainConfig fields")
    parser.add_argument("--out", type=Path, default=Path("checkpoints/prior"), help="output folder")
    parser.add_argument("--steps", type=int, default=None, help="override the number of steps")
    parser.add_argument("--device", choices=["auto", "cpu", "cuda"], default="auto")
    parser.add_argument("--resume", action="store_true", help="continue from OUT/checkpoint.pt")
    parser.add_argument("--export", type=Path, default=None, help="also copy prior.pt here")
    parser.add_argument("--no-progress", action="store_true", help="no tqdm bar")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(message)s")
    cfg = load_config(args.config)
    if args.steps is not None:
        cfg = cfg.model_copy(update={"steps": args.steps})
    try:
        device = resolve_device(args.device, "--device")
    except ValueError as exc:
        raise SystemExit(str(exc)) from None
    arguments = argv if argv is not None else sys.argv[1:]
    command = "python -m mapping.training.train " + " ".join(arguments)
    _, metadata = train(cfg, args.out, device, args.resume, not args.no_progress, command.strip())
    if args.export is not None:
        write_bytes_atomic(args.export, (args.out / "prior.pt").read_bytes())
    log.info(
        "wrote %s (steps %d, %.0f s, held-out mae near surface %.4f vu)",
        args.out / "prior.pt",
        metadata["steps"],
        metadata["train_wall_s"],
        metadata["heldout"]["mae_near_vu"],
    )


if __name__ == "__main__":
    main()
