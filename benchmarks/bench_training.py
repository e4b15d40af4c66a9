"""Training speed: images/s of train.py's loop against a bare forward + backward + optimizer step
of the same network, loss and batch, in the same process (the hardware's limit for this step).

The loop is Lightning's, as `train.py` builds it from ``configs/train.yaml`` (sampler, datamodule
with its decoding workers and augmentation, module, optimizer), run for ``--steps`` steps without
validation or checkpoints on the default synthetic scene (rendered into the cache once). A
callback splits each step into the wait for its batch (data pipeline) and the step itself. The
bare step repeats one batch already in memory: no decoding, no augmentation, no Lightning.

    .venv/bin/python benchmarks/bench_training.py [--steps 20] [--overrides datamodule.num_workers=0 ...]
"""

import argparse
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
    """The config, datamodule and module train.py builds (`training_parts`, `training_module`;
    no validation callback, no scheduler)."""
    from pathlib import Path

    from hydra import compose, initialize_config_dir
    from hydra.utils import instantiate

    from locretrieval.benchmark import BenchmarkSettings
    from locretrieval.config import validated
    from locretrieval.training.relevance import TrainingRelevanceSettings
    from locretrieval.training.run import TrainingSettings, training_module, training_parts

    root = Path(__file__).resolve().parents[1]
    with initialize_config_dir(config_dir=str(root / "configs"), version_base="1.3"):  # the cache of `make train`: .cache/
        cfg = compose("train", overrides=[f"paths.root_dir={root}", "output_dir=/tmp/bench_training", "~scheduler", *overrides])
    descriptor = instantiate(cfg.model)
    parts = training_parts(cfg, instantiate(cfg.data), descriptor.preprocessing, BenchmarkSettings.from_config(cfg),
                           validated(TrainingRelevanceSettings, cfg.train_relevance, "train_relevance"),
                           validated(TrainingSettings, cfg.training, "training"))
    return cfg, parts.datamodule, training_module(cfg, descriptor, parts.pairs)


def loop_images_per_second(cfg, data, module, steps: int) -> tuple[float, float, float]:
    """``(images/s, mean step s, mean batch wait s)`` of Lightning's loop over ``steps`` steps (the first two not timed)."""
    import lightning as L

    timer = StepTimer()
    trainer = L.Trainer(accelerator="cpu", devices=1, max_steps=steps, logger=False, enable_checkpointing=False,
                        enable_progress_bar=False, enable_model_summary=False, callbacks=[timer.callback],
                        use_distributed_sampler=False, num_sanity_val_steps=0)
    data.sampler.batches_per_epoch = steps
    trainer.fit(module, datamodule=data)
    batch = len(next(iter(data.sampler)))
    step, wait = np.mean(timer.steps[2:]), np.mean(timer.waits[2:])
    return batch / (step + wait), float(step), float(wait)


def bare_images_per_second(data, module, steps: int) -> float:
    """Images/s of forward + loss + backward + optimizer step on one batch already decoded."""
    import torch

    images, relevance, negatives, _ = next(iter(data.train_dataloader()))
    optimizer = module.optimizer_factory(params=[p for p in module.network.parameters() if p.requires_grad])
    module.train()
    times = []
    for _ in range(steps):
        start = time.perf_counter()
        loss = module.loss(module(images), relevance, negatives)
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()
        times.append(time.perf_counter() - start)
    torch.set_flush_denormal(True)
    return len(images) / float(np.mean(times[2:]))


def main() -> None:
    import torch

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=20)
    parser.add_argument("--overrides", nargs="*", default=[])
    arguments = parser.parse_args()
    cfg, data, module = training_setup(arguments.overrides)
    torch.set_flush_denormal(True)  # as RetrievalTraining.on_fit_start
    bare = bare_images_per_second(data, module, arguments.steps)
    loop, step, wait = loop_images_per_second(cfg, data, module, arguments.steps)
    print(f"model {cfg.model.name}, batch {len(next(iter(data.sampler)))} images of {list(cfg.datamodule.image_size)}, "
          f"{torch.get_num_threads()} torch threads, {cfg.datamodule.num_workers} decoding workers")
    print(f"bare forward+backward+step: {bare:.1f} images/s")
    print(f"train.py loop: {loop:.1f} images/s ({bare / loop:.2f}x the bare step's time; per step {step:.3f} s computing, "
          f"{wait:.3f} s waiting for the batch)")


if __name__ == "__main__":
    main()
