import numpy as np
import pytest

from cystomap.camera import Camera
from cystomap.errors import InputError


def test_fov_camera_has_requested_diagonal_fov():
    cam = Camera.from_fov(1280, 720, 76.0)
    assert cam.diagonal_fov_deg == pytest.approx(76.0, abs=1e-6)
    assert not cam.calibrated and not cam.has_distortion


def test_projection_of_optical_axis_is_principal_point():
    cam = Camera(640, 480, 500.0, 510.0, 320.3, 240.7, (-0.2, 0.05, 0.001, -0.001, 0.0))
    uv = cam.project(np.array([[0.0, 0.0, 10.0], [1.0, 0.0, 10.0]]))
    assert uv[0] == pytest.approx([320.3, 240.7])
    # barrel distortion (k1 < 0) pulls an off-axis point towards the centre
    assert 320.3 < uv[1, 0] < 320.3 + 500.0 * 0.1


def test_scaled_camera_keeps_fov_and_centre():
    cam = Camera.from_fov(1280, 720, 76.0).scaled(0.25)
    assert (cam.width, cam.height) == (320, 180)
    assert cam.diagonal_fov_deg == pytest.approx(76.0, abs=0.05)
    assert (cam.cx, cam.cy) == pytest.approx((159.5, 89.5))


def test_json_round_trip(tmp_path):
    cam = Camera(320, 180, 230.0, 231.0, 160.0, 90.0, (-0.1, 0.01, 0.0, 0.0, 0.001), name="c")
    assert Camera.load(cam.save(tmp_path / "camera.json")) == cam


@pytest.mark.parametrize(
    ("entry", "message"),
    [
        ({"height": 180, "diagonal_fov_deg": 70}, "missing key 'width'"),
        ({"width": 320, "height": 180}, "diagonal_fov_deg"),
        ({"width": 320, "height": 180, "diagonal_fov_deg": 200}, "not in (1, 179)"),
    ],
)
def test_bad_camera_entries_name_the_camera(entry, message):
    with pytest.raises(InputError, match="camera 'scope'") as err:
        Camera.from_config(entry, name="scope")
    assert message in str(err.value)


@pytest.mark.parametrize("model", ["PINHOLE", "SIMPLE_PINHOLE"])
def test_colmap_round_trip_and_resize_keep_the_opencv_convention(model):
    """A camera written for COLMAP (principal point + 0.5) reads back as the same OpenCV K,
    at its own size and for resized images (as Camera.scaled), and keypoints project alike."""
    import pycolmap

    from cystomap.camera import (
        colmap_params,
        colmap_to_opencv_xy,
        opencv_calibration,
        opencv_to_colmap_xy,
    )

    cam = Camera(320, 240, 250.0, 250.0, 161.3, 117.8)
    pc = pycolmap.Camera(model=model, width=cam.width, height=cam.height,
                         params=list(colmap_params(cam, model)), camera_id=1)
    assert opencv_calibration(pc) == pytest.approx(cam.K)
    half = cam.scaled(0.5)
    assert opencv_calibration(pc, half.width, half.height) == pytest.approx(half.K)
    pts = np.array([[1.0, -2.0, 10.0], [-3.0, 0.5, 7.0]])
    uv_colmap = np.asarray(pc.img_from_cam(pts))
    assert colmap_to_opencv_xy(uv_colmap) == pytest.approx(cam.project(pts))
    assert colmap_to_opencv_xy(uv_colmap, 0.5, 0.5) == pytest.approx(half.project(pts))
    assert opencv_to_colmap_xy(cam.project(pts)) == pytest.approx(uv_colmap)


@pytest.mark.parametrize("model", ["SIMPLE_PINHOLE", "PINHOLE", "SIMPLE_RADIAL", "RADIAL", "OPENCV"])
def test_colmap_models_round_trip(model):
    """COLMAP parameters (pixel corner at 0) <-> Camera (centres at integers), with the
    coefficients each model has; pycolmap projects like Camera.project."""
    import pycolmap

    cam = Camera(640, 360, 470.0, 470.0, 319.5, 179.5, (-0.2, 0.02, 0.0, 0.0, 0.0))
    params = cam.colmap_params(model)
    back = Camera.from_colmap(model, 640, 360, params)
    assert (back.cx, back.cy, back.fx) == pytest.approx((319.5, 179.5, 470.0))
    if model in ("RADIAL", "OPENCV"):
        assert back == cam
    col = pycolmap.Camera.create_from_model_name(1, model, 470.0, 640, 360)
    col.params = list(params)
    pts = np.array([[0.3, -0.2, 1.0], [-0.5, 0.35, 1.0]])
    np.testing.assert_allclose(col.img_from_cam(pts) - 0.5, back.project(pts), atol=1e-6)
