"""host/learn/inputs.py: model inputs from windows and rotation augmentation."""
from __future__ import annotations

import numpy as np
import pytest

from host.learn.inputs import model_inputs
from host.learn.tasks import TrainError
from tests import REPO_ROOT
from tests.windows import synthetic

T = 3


def test_rotated_windows_match_a_drag_in_the_rotated_direction(tmp_path):
    """Rotation augmentation: the 0-degree drag rotated by 30 degrees matches the
    30-degree drag (pins moved by the layout's symmetry, vectors and IMU turned)."""
    from host.data.simulate import simulate_to_dataset
    from host.data.extract import layout_for_profile
    from host.data.load import load_spec
    from host.learn.inputs import augment_rotations, layout_rotations, rotate_windows

    rots = dict(layout_rotations(layout_for_profile("roboskin")))
    assert sorted(rots) == list(range(30, 360, 30))
    base = (REPO_ROOT / "device/sim/scenes/drag-0.toml").read_text()
    ws = {}
    for deg in (0, 30):
        scene = tmp_path / f"d{deg}.toml"
        scene.write_text(base.replace("direction_deg = 0", f"direction_deg = {deg}"))
        simulate_to_dataset(str(scene), tmp_path / f"ds{deg}", seed=0, progress=False)
        ws[deg] = load_spec(str(tmp_path / f"ds{deg}"), "slip", T, progress=False,
                            min_classes=1)
    n = min(len(ws[0]), len(ws[30]))
    want = ws[30].vectors[:n, -1]
    got = rotate_windows(ws[0], 30, rots[30]).vectors[:n, -1]
    wrong = rotate_windows(ws[0], 330, rots[330]).vectors[:n, -1]
    scale = np.abs(want).mean()
    assert np.abs(got - want).mean() < 0.08 * scale < np.abs(wrong - want).mean()
    assert np.allclose(rotate_windows(ws[0], 30, rots[30]).imu[:n], ws[30].imu[:n], atol=1e-3)
    aug = augment_rotations(ws[0], 3)
    assert len(aug) == 4 * len(ws[0]) and aug.source["augmented_deg"] == [0, 90, 180, 270]
    assert np.array_equal(aug.labels[:len(ws[0])], ws[0].labels) and aug.grids is None


def test_model_inputs_name_what_the_windows_lack():
    ws = synthetic(n_pins=5)
    X = model_inputs(ws, "vectors", True)
    assert X.shape == (len(ws), T * 5 * 2 + T * 6) and X.dtype == np.float32
    assert model_inputs(ws, "vectors").shape == (len(ws), T * 5 * 2)
    with pytest.raises(TrainError, match="input_layout must be one of .* got "
                                         "input_layout='pixels'"):
        model_inputs(ws, "pixels")
    with pytest.raises(TrainError, match="input_layout frames needs the binary crops"):
        model_inputs(ws, "frames")
    ws.imu = None
    with pytest.raises(TrainError, match="uses_imu=True but the windows carry no IMU"):
        model_inputs(ws, "vectors", True)
