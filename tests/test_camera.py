import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from quadcast.render.camera import Camera, Frustum, Pose, focal_length_px, gl_matrix, parse_size


def test_identity_pose_view_matrix_is_identity():
    assert np.allclose(Pose([0, 0, 0]).view_matrix(), np.eye(4))


def test_view_matrix_moves_world_into_camera_frame():
    pose = Pose.from_euler([1.0, 2.0, 3.0], pitch_deg=0, yaw_deg=90)  # looking down -X
    assert np.allclose(pose.forward, [-1, 0, 0])
    p_world = np.array([-4.0, 2.0, 3.0, 1.0])  # 5 m in front of the camera
    assert np.allclose(pose.view_matrix() @ p_world, [0, 0, -5, 1])
    assert np.allclose(pose.view_matrix() @ pose.camera_to_world(), np.eye(4))


def test_pitch_looks_up_and_roll_keeps_forward():
    assert np.allclose(Pose.from_euler([0, 0, 0], 90, 0).forward, [0, 1, 0], atol=1e-12)
    assert np.allclose(Pose.from_euler([0, 0, 0], 0, 0, 30).forward, [0, 0, -1])


def test_look_at():
    pose = Pose.look_at([0, 0, 5], [0, 0, 0])
    assert np.allclose(pose.quat, [0, 0, 0, 1]) or np.allclose(pose.quat, [0, 0, 0, -1])
    pose = Pose.look_at([1, 1, 1], [2, 1, 1])
    assert np.allclose(pose.forward, [1, 0, 0])
    with pytest.raises(ValueError, match="coincide"):
        Pose.look_at([0, 0, 0], [0, 0, 0])


def test_symmetric_projection_known_values():
    f = Frustum.symmetric(90.0, 2.0, near=1.0, far=3.0)
    p = f.projection_matrix()
    assert np.allclose(p[0, 0], 0.5) and np.allclose(p[1, 1], 1.0)
    assert np.allclose(p[2, 2], -2.0) and np.allclose(p[2, 3], -3.0)
    # A point on the near plane maps to z_ndc = -1, on the far plane to +1.
    for z, expected in ((-1.0, -1.0), (-3.0, 1.0)):
        clip = p @ [0, 0, z, 1]
        assert np.isclose(clip[2] / clip[3], expected)
    assert np.isclose(f.fovy_deg, 90.0)


def test_off_axis_frustum_centre_ray():
    f = Frustum(-0.1, 0.3, -0.1, 0.1, near=0.1, far=10)
    clip = f.projection_matrix() @ [0.1, 0, -0.1, 1]  # centre of the near window
    assert np.allclose(clip[:2] / clip[3], [0, 0])


def test_focal_lengths_and_unit_extents():
    cam = Camera.perspective(Pose([0, 0, 0]), 160, 90, fovy_deg=60.0, near=0.25)
    fx, fy = cam.focal_px
    assert np.isclose(fy, 45 / np.tan(np.radians(30))) and np.isclose(fx, fy)  # square pixels
    assert np.isclose(focal_length_px(90, 60.0), fy)
    assert np.isclose(focal_length_px(1920, 90.0), 960.0)
    # A point d metres right of the axis at depth z lands fx * d / z pixels right of the centre.
    assert np.allclose(cam.project([[0.3, 0.0, -2.0]]), [[80 + fx * 0.3 / 2.0, 45]])
    f = Frustum(-0.1, 0.3, -0.05, 0.15, near=0.1, far=10)
    assert np.allclose(f.unit_extents, (-1.0, 3.0, -0.5, 1.5))
    assert np.allclose(Camera(Pose([0, 0, 0]), f, 200, 100).focal_px, (50.0, 50.0))
    with pytest.raises(ValueError, match="field of view"):
        focal_length_px(100, 180.0)


def test_linear_depth_inverts_projection():
    f = Frustum.symmetric(60, 1.5, 0.1, 100)
    for z in (0.1, 1.0, 7.5, 99.0):
        clip = f.projection_matrix() @ [0, 0, -z, 1]
        d01 = (clip[2] / clip[3] + 1) / 2
        assert np.isclose(f.linear_depth(np.array([d01]))[0], z, rtol=1e-5)


def test_stereo_eyes_are_ipd_apart_along_camera_x():
    head = Pose.from_euler([0, 1.6, 0], 0, 90)  # camera x axis is world -Z
    left, right = head.stereo_eyes(0.064)
    assert np.isclose(left.distance_to(right), 0.064)
    assert np.allclose(right.position - left.position, [0, 0, -0.064])
    assert np.allclose(left.quat, head.quat)


def test_project_centre_pixel():
    cam = Camera.perspective(Pose([0, 0, 0]), 320, 180)
    assert np.allclose(cam.project([[0, 0, -5]]), [[160, 90]])


def test_gl_matrix_is_column_major():
    m = np.arange(16, dtype=float).reshape(4, 4)
    assert np.allclose(np.frombuffer(gl_matrix(m), "f4"), m.T.reshape(-1))


def test_bad_inputs_name_the_problem():
    with pytest.raises(ValueError, match="Pose.position"):
        Pose([0, 0])
    with pytest.raises(ValueError, match="quaternion"):
        Pose([0, 0, 0], [0, 0, 0, 0])
    with pytest.raises(ValueError, match="near"):
        Frustum(-1, 1, -1, 1, near=0, far=1)
    with pytest.raises(ValueError, match="960x540"):
        parse_size("960by540")
    assert parse_size("320x180") == (320, 180)


def test_quaternion_is_scipy_xyzw():
    pose = Pose([0, 0, 0], Rotation.from_euler("y", 30, degrees=True).as_quat())
    assert np.isclose(pose.angle_to_deg(Pose([0, 0, 0])), 30)
