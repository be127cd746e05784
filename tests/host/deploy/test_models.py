"""host.deploy.models: the profile a release's models carry, and their fused graph."""
from __future__ import annotations

import pytest


def test_a_release_whose_models_carry_another_profile_than_its_config_is_refused(tmp_path):
    """The leg would refuse such models at start; deploy says so before staging,
    naming both profiles (files, pin counts, hashes). A config that sets no profile
    (the default) runs the models' profile."""
    import json
    import shutil

    from device.pi.models.spec import ModelSpec, profile_record
    from host.deploy.options import DeployInputError
    from host.deploy.models import check_models_profile
    from tests import REPO_ROOT
    models = tmp_path / "models"
    shutil.copytree(REPO_ROOT / "models" / "pressure", models / "pressure")
    assert check_models_profile(models, None)["name"] == "roboskin"
    for mf in (models / "pressure").glob("manifest*.json"):
        spec = ModelSpec.from_manifest(json.loads(mf.read_text()), mf)
        spec.profile = {k: v for k, v in profile_record("tactip331").items() if k != "path"}
        mf.write_text(json.dumps(spec.to_manifest()))
    # the default config sets no profile: the leg runs the models' own
    assert check_models_profile(models, None)["n_pins"] == 331
    cfg = tmp_path / "leg.toml"
    cfg.write_text('[models]\nprofile = "roboskin"\n')
    with pytest.raises(DeployInputError, match=r"roboskin\.toml \(roboskin, 133 pins.*is not "
                                               r"the model's: .*pressure/manifest\.json "
                                               r"\(tactip331, 331 pins.*remove "
                                               r"models\.profile"):
        check_models_profile(models, cfg)
    cfg.write_text('[models]\nprofile = "tactip331"\n')
    assert check_models_profile(models, cfg)["n_pins"] == 331


def test_a_release_fuses_the_models_it_ships_and_a_broken_one_is_one_error(tmp_path):
    """The staged models get their fused graph built from the artefacts shipped
    (a stale one that came along is replaced); a model that cannot be fused stops
    the deploy naming its file."""
    import shutil

    from device.pi.models.artefact import read_spec, sha256_file
    from host.deploy.options import DeployInputError
    from host.deploy.models import fuse_release_models
    from tests import REPO_ROOT
    models = tmp_path / "models"
    for t in ("surface", "pressure"):
        shutil.copytree(REPO_ROOT / "models" / t, models / t)
    (models / "fused").mkdir()
    (models / "fused" / "manifest.json").write_text("{}")
    built = fuse_release_models(models)
    rows = read_spec(built["int8"])[0].params.members
    assert {r["task"]: r["sha256"] for r in rows} == {
        t: sha256_file(models / t / "model.int8.onnx") for t in ("surface", "pressure")}
    (models / "pressure" / "model.int8.onnx").write_bytes(b"changed")
    with pytest.raises(DeployInputError, match=r"cannot fuse the models: .*pressure/"
                                               r"model\.int8\.onnx: checksum"):
        fuse_release_models(models)
