"""A manifest.json (or sample.json) that is valid JSON of the wrong structure is an error naming the file and
what to do, never a TypeError from deep inside. No rendering: a rerun checks the folder before it renders."""
import json

import pytest

from datagen.config import make_config
from datagen.generate import generate
from datagen.layout import CameraSetup, DatasetLayout, ManifestError
from dibrpp.io import DataError

TINY = dict(num_objects=1, num_envmaps=1, envs_per_object=1, views=1)


@pytest.mark.parametrize("content", ["5", "[1, 2]", '{"config": 5}', '{"config": [], "generator_version": "1.1.0"}',
                                     '"text"', '{"config": {}, "envmap_sources": 3}'])
def test_rerun_into_a_folder_with_a_malformed_manifest_names_the_file(tmp_path, content):
    out = tmp_path / "ds"
    out.mkdir()
    (out / "manifest.json").write_text(content)
    with pytest.raises(DataError) as e:
        generate(make_config("glossy", **TINY), out, workers=1, progress=False)
    msg = str(e.value)
    assert str(out / "manifest.json") in msg or "different settings" in msg, msg
    assert "\n" not in msg and "object is not" not in msg
    assert (out / "manifest.json").read_text() == content  # left as it was


def test_malformed_envmap_sources_name_the_manifest(tmp_path):
    from datagen.config import config_dict
    from datagen.manifest import GENERATOR_VERSION

    cfg = make_config("glossy", **TINY)
    out = tmp_path / "ds"
    out.mkdir()
    (out / "manifest.json").write_text(json.dumps(dict(config=config_dict(cfg), generator_version=GENERATOR_VERSION,
                                                       envmap_sources=[1, 2])))
    with pytest.raises(DataError, match="manifest.json: 'envmap_sources' is not a list"):
        generate(cfg, out, workers=1, progress=False)


@pytest.mark.parametrize("content", ["[]", "7", '{"files": 3, "views": 1}'])
def test_a_malformed_sample_record_names_the_file(tmp_path, content):
    cfg = make_config("glossy", **TINY)
    out = tmp_path / "ds"
    lay = DatasetLayout(out)
    lay.sample_dir(0, 0).mkdir(parents=True)
    lay.sample_json(0, 0).write_text(content)
    with pytest.raises(DataError, match=r"sample\.json: .*delete .* and rerun"):
        generate(cfg, out, workers=1, progress=False)


GOOD = dict(config=dict(views=2, resolution=16), objects=[dict(index=0, split="train", envmaps=[0], material={})],
            camera=dict(distance=60.0, elevation_deg=27.0, fov=0.69, azimuths_deg=[0.0, 180.0], resolution=16))


@pytest.mark.parametrize("broken,problem", [
    (5, "holds a JSON int"),
    ({**GOOD, "config": 5}, "'config'"),
    ({**GOOD, "config": dict(views="2", resolution=16)}, "config 'views'"),
    ({**GOOD, "objects": 3}, "'objects'"),
    ({**GOOD, "objects": [dict(index=0, split="train", envmaps=4, material={})]}, "an entry of 'objects'"),
    ({**GOOD, "camera": dict(GOOD["camera"], azimuths_deg=4)}, "'camera' is missing or malformed"),
    ({k: v for k, v in GOOD.items() if k != "camera"}, "'camera' is missing"),
])
def test_read_manifest_says_what_is_wrong(tmp_path, broken, problem):
    lay = DatasetLayout(tmp_path)
    lay.manifest.write_text(json.dumps(GOOD))
    assert lay.read_manifest() == GOOD
    lay.manifest.write_text(json.dumps(broken))
    with pytest.raises(ManifestError) as e:
        lay.read_manifest()
    msg = str(e.value)
    assert msg.startswith(f"{lay.manifest}: not a datagen manifest") and problem in msg, msg
    assert "regenerate" in msg


def test_read_manifest_of_a_missing_or_corrupt_file(tmp_path):
    lay = DatasetLayout(tmp_path)
    with pytest.raises(ManifestError, match="no such file"):
        lay.read_manifest()
    lay.manifest.write_text("{not json")
    with pytest.raises(ManifestError, match="corrupt JSON"):
        lay.read_manifest()


def test_camera_setup_of_a_malformed_camera_is_a_clear_value_error():
    with pytest.raises(ValueError, match="'camera' is malformed .*azimuths_deg"):
        CameraSetup.from_manifest({"camera": dict(GOOD["camera"], azimuths_deg=4)})
    with pytest.raises(ValueError, match="'camera' must be an object"):
        CameraSetup.from_manifest({"camera": [1, 2]})
    with pytest.raises(ValueError, match="a manifest must be a JSON object"):
        CameraSetup.from_manifest(3)
