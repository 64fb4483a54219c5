"""The panel's 3D view (viser scene): the rig (app/station/rigview.py computes it) with a legend, framed
so nothing is cut off, and once calibrated the live camera image laid at the camera's image plane, where
a click checks that pixel (viser has no click events on GUI images; scene nodes have them).
"""

from __future__ import annotations

import numpy as np

from app.station.panel_live import image_plane, pixel_of_click
from app.station.rigview import rig_scene
from calib.models.observations import STEP_PROJECTOR

IMAGE_PLANE_NAME = "/rig/camera_image"
IMAGE_PLANE_DEPTH_M = 0.3  # in front of the camera, closer than the boards
VIEW_FOV_DEG = 50.0  # vertical field of view of the initial 3D view
VIEW_ASPECT = 0.55  # width / height of the 3D canvas the view is framed for

SCENE_LEGEND = ("**3D view** (metres, camera frame): blue frustum camera, orange frustum projector, grey frustum "
                "the virtual camera behind the mirror, light blue the mirror, green boards of the mirror step, "
                "orange boards of the projector step, grey boards seen in the mirror (before calibration), orange "
                "lines projector rays. Once calibrated, the live camera image stands in front of the camera: "
                "**click on it to check that pixel** (View from the camera puts it in full view).")


def _remove(scene, name: str) -> None:
    try:
        scene.remove_by_name(name)
    except Exception:  # not there
        pass


def update_rig(server, manifest, result, camera_model) -> None:
    """(Re)draw the rig and frame it for browsers that connect from now on."""
    sc = rig_scene(manifest, result, camera_model)
    k = sc.to_m
    scene = server.scene
    from viser import transforms as vtf

    def pose(T):
        return vtf.SO3.from_matrix(np.asarray(T[:3, :3])).wxyz, np.asarray(T[:3, 3]) * k

    scene.add_frame("/rig", show_axes=False)
    q, p = pose(sc.camera.T_cam_dev)
    scene.add_camera_frustum("/rig/camera", sc.camera.fov_v_rad, sc.camera.aspect, scale=0.08,
                             color=(40, 110, 230), wxyz=q, position=p)
    scene.add_label("/rig/camera/label", "camera", position=(0, -0.08, 0))
    if sc.virtual_camera is not None:
        q, p = pose(sc.virtual_camera.T_cam_dev)
        scene.add_camera_frustum("/rig/virtual_camera", sc.virtual_camera.fov_v_rad, sc.virtual_camera.aspect,
                                 scale=0.08, color=(150, 150, 150), wxyz=q, position=p)
        scene.add_label("/rig/virtual_camera/label", "virtual camera", position=(0, -0.08, 0))
    if sc.mirror_quad is not None:
        v = sc.mirror_quad * k
        scene.add_mesh_simple("/rig/mirror", v.astype(np.float32), np.array([[0, 1, 2], [0, 2, 3]], np.uint32),
                              color=(150, 200, 240), opacity=0.45, side="double")
        scene.add_label("/rig/mirror_label", "mirror", position=tuple(v.mean(axis=0)))
    if sc.projector is not None:
        q, p = pose(sc.projector.T_cam_dev)
        scene.add_camera_frustum("/rig/projector", sc.projector.fov_v_rad, sc.projector.aspect, scale=0.1,
                                 color=(240, 140, 30), wxyz=q, position=p)
        scene.add_label("/rig/projector/label", "projector", position=(0, -0.1, 0))
    if len(sc.rays):
        scene.add_line_segments("/rig/rays", (sc.rays * k).astype(np.float32), (250, 170, 60), thickness=0.002)
    else:
        _remove(scene, "/rig/rays")
    groups = {"mirror step": ((60, 200, 90), []), "projector step": ((240, 150, 40), []),
              "seen in the mirror": ((170, 170, 170), [])}
    for b in sc.boards:
        key = "mirror step" if b.step != STEP_PROJECTOR else ("seen in the mirror" if b.virtual else "projector step")
        groups[key][1].append(b.outline * k)
    for key, (col, quads) in groups.items():
        name = "/rig/boards/" + key.replace(" ", "_")
        if not quads:
            _remove(scene, name)
            _remove(scene, name + "_edges")
            continue
        v = np.concatenate(quads).astype(np.float32)
        f = np.concatenate([np.array([[0, 1, 2], [0, 2, 3]]) + 4 * i for i in range(len(quads))]).astype(np.uint32)
        scene.add_mesh_simple(name, v, f, color=col, opacity=0.35, side="double")
        segs = np.array([[q[i], q[(i + 1) % 4]] for q in quads for i in range(4)], np.float32)
        scene.add_line_segments(name + "_edges", segs, col, thickness=0.002)
    # frame everything drawn (board corners, mirror corners, the devices), with room around it
    pts = [np.zeros(3)] + [q for b in sc.boards for q in b.outline * k]
    if sc.mirror_quad is not None:
        pts += list(sc.mirror_quad * k)
    if sc.projector is not None:
        pts.append(sc.projector.T_cam_dev[:3, 3] * k)
    pts = np.array(pts)
    centre = (pts.min(axis=0) + pts.max(axis=0)) / 2
    extent = float(max(np.ptp(pts, axis=0).max(), 0.6))
    ic = server.initial_camera
    ic.fov = float(np.radians(VIEW_FOV_DEG))
    d = np.array([-0.9, -1.1, -1.0]) / np.linalg.norm([-0.9, -1.1, -1.0])  # behind, above and left
    # the 3D canvas between the two windows is about half as wide as high (1600x1000 page): fit the
    # extent across its width
    dist = 1.6 * extent / (2 * np.tan(np.radians(VIEW_FOV_DEG) / 2) * VIEW_ASPECT)
    ic.look_at = tuple(centre)
    ic.position = tuple(centre + dist * d)
    ic.near = 0.01
    ic.far = 1000.0


def camera_plane(camera):
    """(centre, width_m, height_m, wxyz) of the clickable camera image in the 3D view."""
    return image_plane(camera, IMAGE_PLANE_DEPTH_M)


def click_to_pixel(camera, event) -> tuple[float, float] | None:
    """The camera pixel a click on the image plane points at."""
    return pixel_of_click(camera, IMAGE_PLANE_DEPTH_M, event.ray_origin, event.ray_direction)


def view_from_camera(client, camera) -> None:
    """Put a browser's 3D view at the camera, looking as it looks: the image plane fills the view."""
    fov_v = float(2 * np.arctan2(camera.height / 2.0, camera.fy))
    client.camera.up_direction = (0.0, -1.0, 0.0)
    client.camera.position = (0.0, 0.0, -0.001)
    client.camera.look_at = (0.0, 0.0, IMAGE_PLANE_DEPTH_M)
    client.camera.fov = fov_v * 1.05


def view_whole_rig(server, client) -> None:
    ic = server.initial_camera
    client.camera.up_direction = (0.0, -1.0, 0.0)
    client.camera.position = tuple(ic.position)
    client.camera.look_at = tuple(ic.look_at)
    client.camera.fov = float(np.radians(VIEW_FOV_DEG))
