"""Training speed on the device train.py would use: images/s of its loop against a bare forward +
backward + optimizer step of the same network, loss and batch, in the same process (the hardware's
limit for this step), and the data pipeline alone.

- The loop is Lightning's, as `train.py` builds it from ``configs/train.yaml`` (its trainer:
  ``trainer=auto``, a GPU with mixed precision when there is one; sampler, datamodule with its
  workers reading the decoded-image cache, the augmentation of each batch on the device, module,
  optimizer), run for ``--steps`` steps without validation or checkpoints on the default
  synthetic scene (rendered into the cache once). A callback splits each step into the wait for
  its batch (data pipeline) and the step itself.
- The bare step repeats one batch already on the device (augmented once): no reading, no
  Lightning, under the loop's autocast.
- The pipeline alone: the DataLoader's batches (sampler, workers, collate) with no network, read
  from the decoded cache, beside the same batches decoded from the image files at every step (as
  train.py did before the cache).
- ``--ranks N``: the loop alone on 1 and on N DDP processes (``trainer=ddp``: gloo on the CPU,
  one process per GPU on a machine with several), each process taking ``--steps`` steps of its
  batch, all ranks' batches one global batch (``module.global_batch``); images/s counts every
  rank's images, and the N processes' figure is also given as a multiple of the one process's.

    .venv/bin/python benchmarks/bench_training.py [--steps 20] [--overrides datamodule.num_workers=0 ...]
    .venv/bin/python benchmarks/bench_training.py --ranks 2 [--steps 20] [--overrides ...]
"""

import argparse
import re
import subprocess
import sys
import time

import numpy as np

import locretrieval  # noqa: F401  (config resolvers)


class StepTimer:
    """A Lightning callback timing each training step and the wait for its batch (seconds)."""

    def __init__(self) -> None:
        import lightning as L

        class Callback(L.Callback):
            def on_train_batch_start(inner, trainer, module, batch, index):
                now = time.perf_counter()
                if self.end is not None:
                    self.waits.append(now - self.end)
                self.start = now

            def on_train_batch_end(inner, trainer, module, outputs, batch, index):
                self.end = time.perf_counter()
                self.steps.append(self.end - self.start)

        self.callback = Callback()
        self.waits: list[float] = []
        self.steps: list[float] = []
        self.start = self.end = None


def training_setup(overrides: list[str]):
    """The config, datamodule and module train.py builds (`locretrieval.build.build_training`; no
    scheduler)."""
    from pathlib import Path

    from hydra import compose, initialize_config_dir

    from locretrieval.build import build_training

    root = Path(__file__).resolve().parents[1]
    with initialize_config_dir(
        config_dir=str(root / "configs"), version_base="1.3"
    ):  # the cache of `make train`: .cache/
        cfg = compose(
            "train", overrides=[f"paths.root_dir={root}", "output_dir=/tmp/bench_training", "~scheduler", *overrides]
        )
    run = build_training(cfg)
    return cfg, run.datamodule, run.module


def loop_images_per_second(cfg, data, module, steps: int, processes: int) -> tuple[float, float, float]:
    """``(images/s, mean step s, mean batch wait s)`` of Lightning's loop over ``steps`` steps (the
    first two not timed), on train.py's accelerator and precision, on ``processes`` DDP processes
    (images/s: of all of them; each takes every ``processes``-th batch of the sampler)."""
    import lightning as L

    timer = StepTimer()
    trainer = L.Trainer(
        accelerator=cfg.trainer.accelerator,
        precision=cfg.trainer.precision,
        devices=processes,
        strategy="ddp" if processes > 1 else "auto",
        max_steps=steps,
        logger=False,
        enable_checkpointing=False,
        enable_progress_bar=False,
        enable_model_summary=False,
        callbacks=[timer.callback],
        use_distributed_sampler=False,
        num_sanity_val_steps=0,
    )
    data.sampler.batches_per_epoch = steps * processes
    trainer.fit(module, datamodule=data)
    batch = len(next(iter(data.sampler))) * processes
    step, wait = np.mean(timer.steps[2:]), np.mean(timer.waits[2:])
    return batch / (step + wait), float(step), float(wait)


def bare_images_per_second(cfg, data, module, steps: int) -> float:
    """Images/s of forward + loss + backward + optimizer step on one batch already on the device
    (augmented once), under the loop's precision (float16 autocast and a gradient scaler on a GPU)."""
    import torch

    device = torch.device("cuda" if cfg.trainer.accelerator == "gpu" else "cpu")
    batch = [tensor.to(device) for tensor in next(iter(data.train_dataloader()))]
    images, relevance, negatives, indices = batch
    if data.augmentation is not None:
        images = data.augmentation.augment(images)
    module.to(device).train()
    optimizer = module.optimizer_factory(params=[p for p in module.network.parameters() if p.requires_grad])
    mixed = str(cfg.trainer.precision) == "16-mixed"
    scaler = torch.amp.GradScaler(device.type, enabled=mixed)
    times = []
    for _ in range(steps):
        start = time.perf_counter()
        with torch.autocast(device.type, dtype=torch.float16, enabled=mixed):
            loss = module.batch_loss((images, relevance, negatives, indices))  # the module's loss (and memory)
        optimizer.zero_grad(set_to_none=True)
        scaler.scale(loss).backward()
        scaler.step(optimizer)
        scaler.update()
        if device.type == "cuda":
            torch.cuda.synchronize()
        times.append(time.perf_counter() - start)
    module.cpu()
    return len(images) / float(np.mean(times[2:]))


def pipeline_images_per_second(data, steps: int) -> tuple[float, float]:
    """Images/s of the DataLoader's batches with no network: read from the decoded cache, and
    decoded from the image files at every step (the same sampler, workers and collate)."""
    from torch.utils.data import DataLoader

    from locretrieval.processes import dataloader_workers
    from locretrieval.training.data import collate
    from locretrieval.training.decoded import decode

    class DecodedEveryStep:
        def __len__(self) -> int:
            return len(data.paths)

        def __getitem__(self, index: int):
            import torch

            image = decode(data.paths[index], data.dataset.decoded.shape[2:0:-1])
            return torch.from_numpy(image).permute(2, 0, 1).contiguous(), index

    rates = []
    for dataset in (data.dataset, DecodedEveryStep()):
        loader = DataLoader(
            dataset,
            batch_sampler=data.sampler,
            collate_fn=collate(data.pairs),
            persistent_workers=data.num_workers > 0,
            **dataloader_workers(data.num_workers),  # as the datamodule's: fork
        )
        data.sampler.batches_per_epoch = steps + 2
        batches = iter(loader)
        for _ in range(2):  # the workers start
            next(batches)
        started, count = time.perf_counter(), 0
        for images, *_ in batches:
            count += len(images)
        rates.append(count / (time.perf_counter() - started))
    return rates[0], rates[1]


#: What a run on ``--processes`` prints: its images/s, and what each step took.
LOOP_LINE = re.compile(r"^loop on (\d+) process(?:es)?: ([\d.]+) images/s .*$", re.MULTILINE)


def loop_on_processes(processes: int, steps: int, overrides: list[str]) -> None:
    """Print the `LOOP_LINE` of the training loop on ``processes`` DDP processes (rank 0's; with
    several, Lightning starts the others by running this script again)."""
    import torch

    cfg, data, module = training_setup(overrides)
    torch.set_flush_denormal(True)  # as RetrievalTraining.on_fit_start
    rate, step, wait = loop_images_per_second(cfg, data, module, steps, processes)
    if module.trainer.is_global_zero:
        print(
            f"loop on {processes} process{'es' if processes > 1 else ''}: {rate:.1f} images/s "
            f"(batches of {len(next(iter(data.sampler)))} images per process, per step {step:.3f} s computing, "
            f"{wait:.3f} s waiting; {torch.get_num_threads()} torch threads per process)",
            flush=True,
        )


def ranks_scaling(ranks: int, steps: int, overrides: list[str]) -> None:
    """The training loop on 1 and on ``ranks`` DDP processes, each run in its own process."""
    rates = {}
    for processes in sorted({1, ranks}):
        done = subprocess.run(
            [sys.executable, __file__, "--processes", str(processes), "--steps", str(steps), "--overrides", *overrides],
            capture_output=True,
            text=True,
        )
        found = LOOP_LINE.search(done.stdout)
        if done.returncode or found is None:
            raise RuntimeError(f"the loop on {processes} processes failed:\n{(done.stdout + done.stderr)[-3000:]}")
        rates[processes] = float(found.group(2))
        print(found.group(0), flush=True)
    if ranks > 1:
        print(f"{ranks} processes: {rates[ranks] / rates[1]:.2f}x the images/s of one")


def main() -> None:
    import torch

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=20)
    parser.add_argument("--overrides", nargs="*", default=[])
    parser.add_argument("--ranks", type=int, help="the loop alone on 1 and on this many DDP processes")
    parser.add_argument("--processes", type=int, help=argparse.SUPPRESS)  # one run of --ranks
    arguments = parser.parse_args()
    if arguments.ranks is not None:
        return ranks_scaling(arguments.ranks, arguments.steps, arguments.overrides)
    if arguments.processes is not None:
        return loop_on_processes(arguments.processes, arguments.steps, arguments.overrides)
    cfg, data, module = training_setup(arguments.overrides)
    torch.set_flush_denormal(True)  # as RetrievalTraining.on_fit_start
    device = (
        torch.cuda.get_device_name()
        if cfg.trainer.accelerator == "gpu"
        else f"CPU ({torch.get_num_threads()} torch threads)"
    )
    print(
        f"device: {device}, precision {cfg.trainer.precision}; "
        f"model {cfg.model.name}, batch {len(next(iter(data.sampler)))} images of "
        f"{list(cfg.datamodule.image_size)}, {data.num_workers} DataLoader workers"
    )
    cached, decoded = pipeline_images_per_second(data, arguments.steps)
    print(
        f"data pipeline alone (no network): {cached:.0f} images/s from "
        f"the decoded cache, {decoded:.0f} images/s decoding every image"
    )
    bare = bare_images_per_second(cfg, data, module, arguments.steps)
    loop, step, wait = loop_images_per_second(cfg, data, module, arguments.steps, 1)
    print(f"bare forward+backward+step: {bare:.1f} images/s")
    print(
        f"train.py loop: {loop:.1f} images/s ({bare / loop:.2f}x "
        f"the bare step's time; per step {step:.3f} s computing, "
        f"{wait:.3f} s waiting for the batch)"
    )


if __name__ == "__main__":
    main()
