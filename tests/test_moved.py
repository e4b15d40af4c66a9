"""Module paths that moved keep working (`locretrieval.moved`): those of `locretrieval.models`
before its grouping, of ``locretrieval.localization`` before its split and of the reports of training
runs before they joined `locretrieval.report`, through imports, Hydra's ``_target_``, pickle's
references, a saved run config and a checkpoint that name them."""

import importlib
import pickle
import sys
from dataclasses import asdict
from functools import partial
from pathlib import Path

import helpers
import pytest
import torch
from hydra.utils import get_class, get_object, instantiate
from omegaconf import OmegaConf

import locretrieval.models
from locretrieval.config import built, validated
from locretrieval.models.files.weights import EMBEDDED_CHECKPOINT_KEY, HASH_CACHE_ENV, load_torch_file, save_checkpoint
from locretrieval.models.networks import pooling_settings
from locretrieval.models.published.netvlad import NetVLADDescriptor
from locretrieval.models.trainable.backbones import TorchvisionBackbone
from locretrieval.models.trainable.heads import MixVPRHead
from locretrieval.moved import MOVED_MODULES, current_path
from locretrieval.sfm.settings import SfmSettings
from locretrieval.training.checkpoints import check_resume_checkpoint

PACKAGE = Path(locretrieval.models.__file__).parent
#: The modules of locretrieval/models/ before the grouping (as at commit b6b5b6b, all flat).
FLAT_MODULES = (
    "apgem backbones base delg dense_sift densevlad densevlad_kernels dinov2 efficientnet external extraction "
    "feature_io heads netvlad networks precomputed timm_trunk torch_descriptor trainable vlad weights"
).split()
#: The modules of locretrieval/localization/ before its split (as at commit c50e4f8^).
LOCALIZATION_MODULES = (
    "approximation colmap_model estimates features global_sfm local_sfm matching nearest_neighbours pairs "
    "paradigm pipeline plan pnp pose_cache sfm sparse_map store triangulation verification workers"
).split()
#: The classes a trainable model's architecture recorded before the grouping (0.11 to 0.12).
OLD_BACKBONE = "locretrieval.models.backbones.TorchvisionBackbone"
#: The reports of training runs in locretrieval/training/ before they joined locretrieval/report/: old -> new module.
TRAINING_REPORTS = {"report": "training", "summary": "training_summary", "folders": "training_runs"}
#: A name each of them defines, as a saved config or other code may name it.
REPORT_NAMES = {"report": "TrainingReportSettings", "summary": "write_summary", "folders": "is_training_folder"}
OLD_HEAD = "locretrieval.models.heads.MixVPRHead"


def is_module_here(dotted: str) -> bool:
    """Whether ``locretrieval.models.<...>`` is a file or a package of the package folder today."""
    path = PACKAGE.joinpath(*dotted.removeprefix("locretrieval.models.").split("."))
    return path.with_suffix(".py").is_file() or (path / "__init__.py").is_file()


def test_the_alias_table_names_exactly_the_modules_that_moved_each_at_its_new_place():
    moved = {f"locretrieval.models.{name}" for name in FLAT_MODULES if not is_module_here(name)}
    models = {old: new for old, new in MOVED_MODULES.items() if old.startswith("locretrieval.models.")}
    assert set(models) == moved and len(moved) == 15
    for old, new in models.items():
        assert is_module_here(new) and new.rsplit(".", 1)[1] == old.rsplit(".", 1)[1]  # the same file, moved
    split = {f"locretrieval.localization.{name}" for name in LOCALIZATION_MODULES} | {"locretrieval.localization"}
    reports = {f"locretrieval.training.{old}" for old in TRAINING_REPORTS}
    assert set(MOVED_MODULES) == set(models) | split | reports | {"locretrieval.sfm.forecast"}
    assert not (PACKAGE.parent / "sfm" / "forecast.py").exists()
    assert not (PACKAGE.parent / "localization").exists()
    for old, new in TRAINING_REPORTS.items():
        assert not (PACKAGE.parent / "training" / f"{old}.py").exists()
        assert (PACKAGE.parent / "report" / f"{new}.py").is_file()


@pytest.mark.parametrize("old", sorted(TRAINING_REPORTS))
def test_every_report_module_that_left_training_imports_its_module_in_report(old):
    old, new = f"locretrieval.training.{old}", f"locretrieval.report.{TRAINING_REPORTS[old]}"
    assert MOVED_MODULES[old] == new
    module = importlib.import_module(new)
    sys.modules.pop(old, None)  # as in a fresh interpreter: the first import of the old name
    with pytest.warns(DeprecationWarning, match=f"{old} is now {new}"):
        assert importlib.import_module(old) is module
    name = REPORT_NAMES[old.rsplit(".", 1)[1]]
    assert module.__name__ == new and get_object(f"{old}.{name}") is getattr(module, name)


def test_the_forecast_that_left_sfm_imports_its_module_in_paradigms():
    old, new = "locretrieval.sfm.forecast", "locretrieval.paradigms.forecast"
    module = importlib.import_module(new)
    sys.modules.pop(old, None)  # as in a fresh interpreter: the first import of the old name
    with pytest.warns(DeprecationWarning, match=f"{old} is now {new}"):
        assert importlib.import_module(old) is module
    assert get_object(f"{old}.dry_run_forecast") is module.dry_run_forecast


@pytest.mark.parametrize("name", LOCALIZATION_MODULES)
def test_every_module_of_the_split_localization_package_imports_its_successor(name):
    old, new = f"locretrieval.localization.{name}", MOVED_MODULES[f"locretrieval.localization.{name}"]
    module = importlib.import_module(new)
    assert importlib.import_module(old) is module and module.__name__ == new
    assert importlib.import_module("locretrieval.localization") is importlib.import_module("locretrieval.paradigms")


def test_a_saved_sfm_section_naming_the_localization_package_builds_todays_parts():
    """A run of 0.11 saved ``sfm.features._target_: locretrieval.localization.features.SiftFeatures``
    and the like: its section validates into the settings of today's paths, equal to them."""
    today = OmegaConf.to_container(helpers.compose_config("evaluate").sfm, resolve=True)
    saved = OmegaConf.create(today)
    renamed = 0
    for part in ("features", "query_verification", "database_verification", "triangulation"):
        target = saved[part]["_target_"]
        assert target.startswith("locretrieval.sfm.")
        saved[part]["_target_"] = target.replace("locretrieval.sfm.", "locretrieval.localization.")
        renamed += 1
    settings = validated(SfmSettings, saved, "sfm")
    assert renamed == 4 and settings == validated(SfmSettings, OmegaConf.create(today), "sfm")
    assert type(settings.features).__module__ == "locretrieval.sfm.features"


@pytest.mark.parametrize("name", FLAT_MODULES)
def test_every_old_module_path_imports_the_module_of_today_itself(name):
    old = f"locretrieval.models.{name}"
    new = MOVED_MODULES.get(old, old)
    module = importlib.import_module(new)
    if old in MOVED_MODULES:
        sys.modules.pop(old, None)  # as in a fresh interpreter: the first import of the old name
        with pytest.warns(DeprecationWarning, match=f"{old} is now {new}"):
            assert importlib.import_module(old) is module
    assert importlib.import_module(old) is module and sys.modules[old] is module
    assert module.__name__ == module.__spec__.name == new  # the module keeps its own name and spec


def test_a_fresh_interpreter_resolves_old_paths_by_import_pickle_and_hydra():
    code = (
        "import pickle\n"
        "import locretrieval.models.heads as old\n"
        "import locretrieval.models.trainable.heads as new\n"
        "from locretrieval.models.precomputed import PrecomputedDescriptor\n"
        "from locretrieval.models import PrecomputedDescriptor as public\n"
        "from hydra.utils import get_class\n"
        "assert old is new and PrecomputedDescriptor is public\n"
        "assert pickle.loads(b'clocretrieval.models.backbones\\nTimmBackbone\\n.') is "
        "get_class('locretrieval.models.trainable.backbones.TimmBackbone')\n"
        "assert get_class('locretrieval.models.netvlad.NetVLADDescriptor').__module__ == "
        "'locretrieval.models.published.netvlad'\n"
        "print('ok')\n"
    )
    process = helpers.run_python(code)
    assert process.returncode == 0 and process.stdout.strip() == "ok", process.stderr


def test_hydra_and_pickle_build_the_classes_of_today_from_old_paths():
    assert get_class("locretrieval.models.netvlad.NetVLADDescriptor") is NetVLADDescriptor
    assert pickle.loads(b"clocretrieval.models.heads\nMixVPRHead\n.") is MixVPRHead
    head = instantiate({"_target_": OLD_HEAD, "channels": 8, **mixvpr_options()})
    assert type(head) is MixVPRHead
    # settings given by an old path are recorded by today's (an architecture, a cache key)
    assert pooling_settings({"_target_": OLD_HEAD, **mixvpr_options()}) == pooling_settings(
        partial(MixVPRHead, **mixvpr_options())
    )
    assert current_path(OLD_HEAD) == "locretrieval.models.trainable.heads.MixVPRHead"
    assert current_path("locretrieval.models.networks.GeMPooling") == "locretrieval.models.networks.GeMPooling"
    assert current_path("locretrieval.models.densevlad_kernels") == "locretrieval.models.published.densevlad_kernels"


def mixvpr_options() -> dict:
    node = OmegaConf.to_container(OmegaConf.load(helpers.CONFIGS / "model" / "pooling" / "mixvpr.yaml"))
    return {key: value for key, value in node.items() if not key.startswith("_")}


def saved_run_config(folder: Path, *overrides: str) -> Path:
    """evaluate.py's resolved ``config.yaml`` of a MixVPR head on ResNet-18, as a run writes it."""
    cfg = helpers.evaluate_config(
        "model=gem",
        "model/pooling=mixvpr",
        "model.backbone.name=resnet18",
        f"paths.root_dir={folder}",
        *helpers.QUIET_EXTRACTION,
        *overrides,
    )
    folder.mkdir(parents=True)
    OmegaConf.save(cfg, folder / "config.yaml", resolve=True)
    return folder / "config.yaml"


def test_a_run_config_and_a_checkpoint_written_with_old_module_paths_load_as_todays(tmp_path, monkeypatch):
    """A run of 0.11-0.12 saved its config with the old ``_target_`` paths and its checkpoint's
    architecture names the classes by them: the model evaluate.py builds from them is today's,
    equal to the one of the new paths, and train.py resumes from the checkpoint."""
    monkeypatch.setenv(HASH_CACHE_ENV, str(tmp_path / "hashes"))
    trained = built(OmegaConf.load(saved_run_config(tmp_path / "new", "model.random_init=true")).model, "model")
    old_architecture = {
        **trained.architecture,
        "backbone": {**trained.architecture["backbone"], "_target_": OLD_BACKBONE},
        "pooling": {**trained.architecture["pooling"], "_target_": OLD_HEAD},
    }
    checkpoint = tmp_path / "old.pt"
    save_checkpoint(
        checkpoint, trained.model, old_architecture, asdict(trained.preprocessing), trained.network.state_dict()
    )
    # the saved config of an old run: its targets the old paths, the model read from the old checkpoint
    config = saved_run_config(tmp_path / "old", f"model.weights={checkpoint}")
    text = config.read_text()
    for new in ("locretrieval.models.trainable.backbones.TorchvisionBackbone", "locretrieval.models.trainable.heads."):
        assert new in text
    text = text.replace("locretrieval.models.trainable.backbones.", "locretrieval.models.backbones.")
    config.write_text(text.replace("locretrieval.models.trainable.heads.", "locretrieval.models.heads."))
    old_model = built(OmegaConf.load(config).model, "model")  # evaluate.py's line
    new_model = built(
        OmegaConf.load(saved_run_config(tmp_path / "today", f"model.weights={checkpoint}")).model, "model"
    )

    assert type(old_model.network.pooling) is MixVPRHead and type(new_model.network.pooling) is MixVPRHead
    assert old_model.architecture == new_model.architecture == trained.architecture
    assert old_model.architecture["backbone"] == {
        "_target_": "locretrieval.models.trainable.backbones.TorchvisionBackbone",
        **asdict(TorchvisionBackbone("resnet18")),
    }
    assert old_model.identity() == new_model.identity()  # one descriptor cache key
    images = torch.rand(2, 3, 64, 80, generator=torch.Generator().manual_seed(0))
    with torch.no_grad():
        expected = trained.network.eval()(images)
        torch.testing.assert_close(old_model.network.eval()(images), expected, rtol=0, atol=0)
        torch.testing.assert_close(new_model.network.eval()(images), expected, rtol=0, atol=0)

    # train.py's Lightning checkpoint embeds the same record; resuming from an old one is accepted
    lightning = tmp_path / "last.ckpt"
    torch.save({EMBEDDED_CHECKPOINT_KEY: load_torch_file(checkpoint), "state_dict": {}}, lightning)
    check_resume_checkpoint(lightning, new_model.model, new_model.architecture)
    with pytest.raises(ValueError, match=r"ckpt_path: .*architecture in the file differs .*pooling"):
        check_resume_checkpoint(
            lightning, new_model.model, {**new_model.architecture, "pooling": {"_target_": OLD_HEAD, "blocks": 1}}
        )
