"""The LightningModule: a descriptor network (`models.networks.RetrievalNet`) trained with a
ranking loss on batches of images and their ground-truth relevance."""

from __future__ import annotations

import fnmatch
import logging
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import asdict
from typing import Any

import lightning as L
import torch

from locretrieval.config import SettingError
from locretrieval.models.extraction import Preprocessing, describe_batch
from locretrieval.models.files.weights import CHECKPOINT_FORMAT, EMBEDDED_CHECKPOINT_KEY, plain
from locretrieval.models.networks import RetrievalNet
from locretrieval.training.relevance import TrainingPairs

log = logging.getLogger(__name__)


def check_patterns(network: torch.nn.Module, patterns: Iterable[str], key: str) -> None:
    """Raise unless every shell-style ``pattern`` matches a parameter name of ``network``; the
    error names ``key`` (the setting) and some names."""
    names = [name for name, _ in network.named_parameters()]
    for pattern in patterns:
        if not any(fnmatch.fnmatchcase(name, pattern) for name in names):
            raise SettingError(
                key,
                f"{pattern!r} matches no parameter of the network "
                f"(names are like {names[0]!r}, {names[len(names) // 2]!r}, {names[-1]!r})",
            )


def freeze_parameters(network: torch.nn.Module, patterns: Sequence[str]) -> list[str]:
    """Keep the parameters whose names match a shell-style ``pattern`` (``backbone.blocks.[0-9].*``)
    fixed; returns their names. A pattern that matches no parameter is an error naming some."""
    check_patterns(network, patterns, "frozen")
    frozen = []
    for name, parameter in network.named_parameters():
        if any(fnmatch.fnmatchcase(name, pattern) for pattern in patterns):
            parameter.requires_grad_(False)
            frozen.append(name)
    return frozen


def _world_size() -> int:
    """The processes of the run (DDP's process group), 1 without one."""
    distributed = torch.distributed.is_available() and torch.distributed.is_initialized()
    return torch.distributed.get_world_size() if distributed else 1


class TrainingDiverged(RuntimeError):
    """A non-finite loss or gradient: training stops at that step, nothing is updated with it."""


class RetrievalTraining(L.LightningModule):
    """Trains ``network`` with ``loss(descriptors, relevance, negatives)``.

    Images arrive as ``uint8`` RGB and go through ``preprocessing.normalize``, the normalisation
    evaluation uses. ``optimizer``/``scheduler``: partial constructors (Hydra ``_partial_``)
    taking the parameters / the optimizer. Every Lightning checkpoint also holds, under
    `EMBEDDED_CHECKPOINT_KEY`, a plain checkpoint of model ``model`` with ``architecture`` that the
    zoo loader reads (``evaluate.py model=gem model.weights=<ckpt>``).
    ``freeze_batch_norm``: batch-norm layers stay in eval mode while training (the pretrained
    running statistics normalise every batch and are never updated; their affine parameters
    still learn), as retrieval fine-tuning does with small batches (Radenovic et al., TPAMI 2019).
    ``frozen``: shell patterns of parameter names kept fixed (`freeze_parameters`);
    ``compile_network``: ``torch.compile`` the network's forward pass.
    ``head_lr_scale``: the learning rate of the parameters outside the backbone (pooling or head,
    whitening, projection) is the optimizer's times this (and follows the same schedule): a head
    that starts random can learn faster than the pretrained trunk.
    ``lr_scales``: a learning rate per part of any network: ``{shell pattern of parameter names:
    factor}``, e.g. ``{'module.aggregation.*': 10}``; a parameter takes the factor of the first
    pattern it matches (before ``head_lr_scale``), each part follows the same schedule.
    ``memory``: a partial loss wrapper (Hydra ``_partial_``) taking the loss and the training
    ``pairs``: the cross-batch memory (`training.memory.CrossBatchMemory`), which ranks every
    batch's anchors against the last training images seen too; ``None``: each anchor is ranked
    against its batch only.
    ``global_batch``: under DDP, each step's loss, and the memory, see the union of every rank's
    batch (in rank order, their relevance read from ``pairs``; the descriptors gathered with their
    gradients, so that the step is the one a single process takes on the union); false: each
    rank's loss sees its own batch (the gradients are averaged over ranks).
    """

    def __init__(
        self,
        network: RetrievalNet,
        preprocessing: Preprocessing,
        loss: torch.nn.Module,
        optimizer: Callable[..., torch.optim.Optimizer],
        scheduler: Callable[..., Any] | None,
        model: str,
        architecture: Mapping[str, Any],
        *,
        memory: Callable[..., torch.nn.Module] | None,
        compile_network: bool,
        freeze_batch_norm: bool,
        frozen: Sequence[str],
        head_lr_scale: float,
        lr_scales: Mapping[str, float] | None,
        global_batch: bool,
        pairs: TrainingPairs | None = None,
    ) -> None:
        super().__init__()
        names = freeze_parameters(network, frozen)
        if names:
            log.info("%d of %d parameter tensors frozen (module.frozen)", len(names), len(list(network.parameters())))
        self.network = network
        self.forward_network = torch.compile(network) if compile_network else network
        self.preprocessing = preprocessing
        if memory is not None and pairs is None:
            raise ValueError("module.memory needs the training pairs (train.py gives them)")
        self.remembers = memory is not None  # the loss takes the batch's indices (what it remembers)
        self.loss = memory(loss=loss, pairs=pairs) if self.remembers else loss
        self.optimizer_factory, self.scheduler_factory = optimizer, scheduler
        self.model_name, self.architecture = model, plain(dict(architecture))
        self.freeze_batch_norm = freeze_batch_norm
        if not head_lr_scale > 0:
            raise ValueError(f"module.head_lr_scale must be positive, got {head_lr_scale}")
        if head_lr_scale != 1 and not hasattr(network, "backbone"):
            raise ValueError(
                f"module.head_lr_scale={head_lr_scale} needs a network with a backbone and a head "
                f"(a zoo model's RetrievalNet); {type(network).__name__} has no 'backbone'"
            )
        self.head_lr_scale = float(head_lr_scale)
        self.lr_scales = {str(pattern): float(factor) for pattern, factor in (lr_scales or {}).items()}
        check_patterns(network, self.lr_scales, "lr_scales")
        if any(not factor > 0 for factor in self.lr_scales.values()):
            raise ValueError(f"module.lr_scales factors must be positive, got {self.lr_scales}")
        self.global_batch = bool(global_batch)
        self.pairs = pairs

    def train(self, mode: bool = True) -> RetrievalTraining:
        super().train(mode)
        if mode and self.freeze_batch_norm:
            for layer in self.network.modules():
                if isinstance(layer, torch.nn.modules.batchnorm._BatchNorm):
                    layer.eval()
        return self

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        """Unit descriptors ``[B, D]`` of ``uint8 [B, 3, H, W]`` images, computed as extraction does
        (normalisation, every scale of ``preprocessing``), with gradients."""
        return describe_batch(self.forward_network, images, self.preprocessing)

    def on_fit_start(self) -> None:
        # Gradients of the margin losses drive activations into denormal floats, which CPUs
        # compute up to ~3x slower (measured: 10.5 s vs 3.9 s per batch); flush them to zero.
        torch.set_flush_denormal(True)
        self.train()  # Lightning keeps the modes it finds: freeze batch norm here
        if self.global_batch and self.trainer.world_size > 1 and self.pairs is None:
            raise ValueError("module.global_batch under DDP needs the training pairs (train.py gives them)")

    def batch_loss(self, batch: tuple[torch.Tensor, ...]) -> torch.Tensor:
        """The loss of a batch ``(images, relevance, negatives, indices)`` (`training.data.collate`),
        under DDP with ``global_batch`` the union of every rank's (`union_of_batches`); a loss with a
        memory also takes the batch's indices (it ranks against the remembered images, then
        remembers the batch)."""
        images, relevance, negatives, indices = batch
        descriptors = self(images)
        if self.global_batch and _world_size() > 1:
            descriptors, relevance, negatives, indices = self.union_of_batches(descriptors, indices)
        if self.remembers:
            return self.loss(descriptors, relevance, negatives, indices)
        return self.loss(descriptors, relevance, negatives)

    def union_of_batches(
        self, descriptors: torch.Tensor, indices: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """Every rank's batch, in rank order: ``(descriptors, relevance, negatives, indices)`` as
        `collate` makes them for one batch of all their images. The descriptors are gathered with
        their gradients: each rank's loss is the same function of all of them, and the gradient of
        a rank's descriptors, summed over the ranks' losses by the gather's backward pass, then
        averaged over ranks by DDP, is that of one process's loss on the union."""
        descriptors = self.all_gather(descriptors, sync_grads=True).flatten(0, 1)
        indices = self.all_gather(indices).flatten(0, 1)
        relevance, negatives = (
            torch.from_numpy(block).to(descriptors.device) for block in self.pairs.batch(indices.cpu().numpy())
        )
        return descriptors, relevance, negatives, indices

    def training_step(self, batch: tuple[torch.Tensor, ...], batch_index: int) -> torch.Tensor:
        loss = self.batch_loss(batch)
        images = batch[0]
        finite = bool(torch.isfinite(loss))
        if self.trainer.world_size > 1:  # every rank stops together (one rank alone would hang the others)
            finite = self.trainer.strategy.reduce_boolean_decision(finite, all=True)
        if not finite:
            what = "the loss of another rank is not finite" if torch.isfinite(loss) else f"the loss is {loss.item()}"
            raise TrainingDiverged(self._divergence(what))
        self.log("train/loss", loss, prog_bar=True, batch_size=len(images))
        return loss

    def on_before_optimizer_step(self, optimizer: torch.optim.Optimizer) -> None:
        """Stop before the optimizer step when a gradient is not finite (the weights stay as they
        were). Gradients are unscaled here; with mixed precision a non-finite one is the gradient
        scaler's to skip, as it does in its first steps, so there is no check."""
        if "mixed" in str(self.trainer.precision) or str(self.trainer.precision).startswith("16"):
            return
        for name, parameter in self.network.named_parameters():
            if parameter.grad is not None and not torch.isfinite(parameter.grad).all():
                raise TrainingDiverged(self._divergence(f"the gradient of {name} is not finite"))

    def _divergence(self, what: str) -> str:
        rates = sorted({group["lr"] for optimizer in self.trainer.optimizers for group in optimizer.param_groups})
        return (
            f"training diverged at step {self.global_step} (epoch {self.current_epoch}): {what}, learning rate {rates} "
            f"(module.optimizer.lr); lower module.optimizer.lr. The checkpoints in checkpoints/ are from before it."
        )

    def configure_optimizers(self):
        optimizer = self.optimizer_factory(params=self._parameter_groups())
        for group in optimizer.param_groups:  # before the scheduler records each group's initial lr
            group["lr"] *= group.get("lr_scale", 1.0)
        if self.scheduler_factory is None:
            return optimizer
        return {"optimizer": optimizer, "lr_scheduler": self.scheduler_factory(optimizer=optimizer)}

    def _parameter_groups(self) -> list[torch.nn.Parameter] | list[dict[str, Any]]:
        """The trainable parameters of the network and of the loss (a learned temperature or
        margin): one group without ``lr_scales`` and with ``head_lr_scale`` 1 (the optimizer state
        of earlier runs resumes), else named groups with their ``lr_scale``: one per pattern of
        ``lr_scales`` that takes parameters, then ``backbone`` and ``head`` (the rest of the
        network; ``network`` when ``head_lr_scale`` is 1) and ``loss``, each where it has any."""
        trainable = [(name, p) for name, p in self.network.named_parameters() if p.requires_grad]
        learned_loss = (
            [p for p in self.loss.parameters() if p.requires_grad] if isinstance(self.loss, torch.nn.Module) else []
        )
        if self.head_lr_scale == 1 and not self.lr_scales:
            return [p for _, p in trainable] + learned_loss
        trunk = {id(p) for p in self.network.backbone.parameters()} if self.head_lr_scale != 1 else set()
        groups: dict[str, dict[str, Any]] = {}
        for name, parameter in trainable:
            pattern = next((pattern for pattern in self.lr_scales if fnmatch.fnmatchcase(name, pattern)), None)
            if pattern is not None:
                part, scale = pattern, self.lr_scales[pattern]
            elif self.head_lr_scale == 1:
                part, scale = "network", 1.0
            else:
                part, scale = ("backbone", 1.0) if id(parameter) in trunk else ("head", self.head_lr_scale)
            groups.setdefault(part, {"params": [], "name": part, "lr_scale": scale})["params"].append(parameter)
        if learned_loss:
            groups["loss"] = {"params": learned_loss, "name": "loss", "lr_scale": 1.0}
        return list(groups.values())

    def on_save_checkpoint(self, checkpoint: dict[str, Any]) -> None:
        checkpoint[EMBEDDED_CHECKPOINT_KEY] = {
            "format": CHECKPOINT_FORMAT,
            "model": self.model_name,
            "architecture": self.architecture,
            "preprocessing": plain(asdict(self.preprocessing)),
            # the tensors of the Lightning checkpoint's own state_dict: torch.save writes each storage once
            "state_dict": dict(self.network.state_dict()),
            "extra": {},
        }
