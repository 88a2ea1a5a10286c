"""Blender data for a capture: one collection, a root empty, one camera per photo, the two
slab planes and the sparse points; and the reverse, a Blender camera as a pinhole in the
model's COLMAP frame.  Objects are found again by their `neulf_role` / `neulf_view`
custom properties, so importing twice updates instead of duplicating; a capture camera also
keeps the name the import gave it (`neulf_object`), since a copy of it (Shift+D) carries the
same properties and is the artist's camera, not the photo's."""

from __future__ import annotations

from pathlib import Path

import bpy
import numpy as np
from mathutils import Matrix

from . import convert
from .convert import refuse_uneven_scale
from ..neulf_core.errors import NeulfError

ROLE = "neulf_role"
OBJECT_NAME = "neulf_object"
CAMERAS = "neulf_cameras"  # on the capture's collection: photo name -> its camera object (a pointer)
CLIP_START_DEFAULT = 0.1  # a new camera's, Blender 4.2 and 5.0


def _matrix(array) -> Matrix:
    return Matrix([list(map(float, row)) for row in np.asarray(array).reshape(4, 4)])


def find_capture(scene):
    """(collection, root) of the imported capture, or (None, None).  Pointers, so renaming
    either keeps the link and a full copy of the scene finds its own copies; a .blend saved
    before them names them (read here, replaced at the next import)."""
    props = scene.neulf
    collection, root = props.capture_collection, props.root
    if collection is None and props.collection_name:
        collection = bpy.data.collections.get(props.collection_name)
    if root is None and props.root_name:
        root = bpy.data.objects.get(props.root_name)
    return collection, root


def _ensure_collection(scene, name: str, fingerprint: str):
    """The capture's collection in this scene (found by the scene's fingerprint), or a new one:
    another scene importing the same capture gets objects of its own, so turning one scene's
    root does not turn the other's."""
    own = find_capture(scene)[0]
    collection = own if own is not None and own.get("neulf_fingerprint") == fingerprint else next(
        (c for c in scene.collection.children_recursive if c.get("neulf_fingerprint") == fingerprint), None)
    if collection is None:
        collection = bpy.data.collections.new(name)
        collection["neulf_fingerprint"] = fingerprint
    if collection.name not in scene.collection.children and not any(
            c == collection for c in scene.collection.children_recursive):
        scene.collection.children.link(collection)
    return collection


def is_capture_camera(obj) -> bool:
    """One of the capture's own cameras (its pose is its photo's): not a copy an artist made of
    one (Shift+D), which carries the same properties.  The capture's collection points at its
    own cameras (CAMERAS), so a renamed one stays its photo's; a file imported before the
    pointers tells them by the name the import gave."""
    if obj is None or obj.get(ROLE) != "camera":
        return False
    view = obj.get("neulf_view")
    for collection in obj.users_collection:
        own = collection.get(CAMERAS)
        if own is not None and view in own:
            return own[view] == obj
    given = obj.get(OBJECT_NAME)
    if given is None:  # (imported before the name was kept: the import named cameras after their photos)
        return obj.name == Path(str(obj.get("neulf_view", ""))).stem
    return given == obj.name


def _members(collection) -> dict:
    found, cameras = {}, {}
    for obj in collection.objects:
        if obj.get(ROLE) == "camera":
            cameras.setdefault(obj.get("neulf_view"), []).append(obj)
        elif obj.get(ROLE):
            found.setdefault((obj[ROLE], None), obj)  # (the first: a Shift+D copy comes after its original)
    pointers = collection.get(CAMERAS)
    for view, claiming in cameras.items():
        own = [obj for obj in claiming if is_capture_camera(obj)]
        if not own and len(claiming) == 1 and (OBJECT_NAME not in claiming[0] or pointers is None or view not in pointers):
            own = claiming  # (an older import's camera, renamed: the only one there is)
        if own:
            found[("camera", view)] = own[0]
    return found


def _own_root(scene, collection, members):
    """The capture's root: the scene's pointer where it is this collection's (a Shift+D copy of
    the root carries the same role; a root deleted with X survives, held by the pointer, and is
    linked back), else the collection's first root."""
    own_collection, pointed = find_capture(scene)
    if pointed is not None and pointed.get(ROLE) == "root" and own_collection == collection:
        if collection not in pointed.users_collection:
            collection.objects.link(pointed)
        return pointed
    return members.get(("root", None))


def _mesh_object(collection, members, role: str, name: str, vertices, faces, root):
    mesh = bpy.data.meshes.new(name)
    mesh.from_pydata([tuple(map(float, v)) for v in vertices], [], faces)
    mesh.update()
    obj = members.get((role, None))
    if obj is None:
        obj = bpy.data.objects.new(name, mesh)
        collection.objects.link(obj)
        obj[ROLE] = role
    else:
        old = obj.data
        obj.data = mesh
        if old.users == 0:
            bpy.data.meshes.remove(old)
    obj.parent = root
    obj.matrix_parent_inverse = Matrix.Identity(4)
    obj.matrix_basis = Matrix.Identity(4)
    return obj


def set_slab_planes(collection, root, slab: dict) -> None:
    """The uv and st planes as wireframe quads at the slab's world corners (model frame)."""
    members = _members(collection)
    for plane in ("uv", "st"):
        corners = np.asarray(slab[f"{plane}_corners_world"], dtype=np.float64)
        obj = _mesh_object(collection, members, f"{plane}_plane", f"NeuLF {plane} plane", corners, [(0, 1, 2, 3)], root)
        obj.display_type = "WIRE"
        obj.show_name = True
        obj.hide_render = True


def apply_capture_camera(scene, camera_obj) -> bool:
    """Set the scene's resolution and pixel aspect to the photo size of an imported camera."""
    size, K = camera_obj.get("neulf_size"), camera_obj.get("neulf_K")
    if size is None or K is None:
        return False
    fx, fy, cx, cy = (float(v) for v in K)
    settings = convert.blender_camera_from_K(fx, fy, cx, cy, int(size[0]), int(size[1]))
    render = scene.render
    render.resolution_x, render.resolution_y = settings["resolution_x"], settings["resolution_y"]
    render.resolution_percentage = 100
    render.pixel_aspect_x, render.pixel_aspect_y = settings["pixel_aspect_x"], settings["pixel_aspect_y"]
    return True


def build_capture(context, description: dict, *, import_points: bool = True):
    """Create or update the capture's objects from `Service.describe_scene`'s result."""
    scene = context.scene
    root_path = Path(description["root"])
    collection = _ensure_collection(scene, f"NeuLF {root_path.name}", description["fingerprint"])
    members = _members(collection)

    root = _own_root(scene, collection, members)
    # (the capture's objects already here: a re-import, which leaves the artist's camera, size and colours)
    first_import = root is None and not any(role == "camera" for role, _ in members)
    if root is None:
        root = bpy.data.objects.new(f"NeuLF Root {root_path.name}", None)
        root.empty_display_type = "ARROWS"
        collection.objects.link(root)
        root[ROLE] = "root"
        # COLMAP's world is y-down, z-forward: turn it so the capture stands upright in Blender.
        root.matrix_world = Matrix.Rotation(-np.pi / 2, 4, "X")
    views = description["views"]
    centres = np.array([-np.asarray(v["R"]).T @ np.asarray(v["t"]) for v in views])
    spacing = float(np.median(np.linalg.norm(centres - centres.mean(0), axis=1))) if len(views) > 1 else 1.0
    root.empty_display_size = max(spacing, 1e-3)

    keep = set()
    for view in views:
        name = view["name"]
        keep.add(name)
        obj = members.get(("camera", name))
        if obj is None:
            data = bpy.data.cameras.new(Path(name).stem)
            obj = bpy.data.objects.new(Path(name).stem, data)
            collection.objects.link(obj)
            obj[ROLE] = "camera"
            obj["neulf_view"] = name
        obj[OBJECT_NAME] = obj.name
        if collection.get(CAMERAS) is None:
            collection[CAMERAS] = {}
        collection[CAMERAS][name] = obj
        K = np.asarray(view["K"], dtype=np.float64)
        fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
        settings = convert.blender_camera_from_K(fx, fy, cx, cy, view["width"], view["height"])
        data = obj.data
        data.sensor_fit = settings["sensor_fit"]
        data.sensor_width = settings["sensor_width"]
        data.lens = settings["lens"]
        data.shift_x, data.shift_y = settings["shift_x"], settings["shift_y"]
        data.display_size = max(0.3 * spacing, 1e-3)
        obj["neulf_K"] = [float(fx), float(fy), float(cx), float(cy)]
        obj["neulf_size"] = [int(view["width"]), int(view["height"])]
        if view.get("image_path"):
            obj["neulf_image"] = view["image_path"]
        obj.parent = root
        obj.matrix_parent_inverse = Matrix.Identity(4)
        obj.matrix_basis = _matrix(convert.matrix_from_pose(view["R"], view["t"]))
    for (role, name), obj in list(members.items()):
        if role == "camera" and name not in keep:
            bpy.data.objects.remove(obj)
    own = collection.get(CAMERAS)
    for name in [name for name in own.keys() if name not in keep or own[name] is None]:
        del own[name]

    set_slab_planes(collection, root, description["slab"])
    points = np.asarray(description.get("points", np.zeros((0, 3))), dtype=np.float64).reshape(-1, 3)
    if import_points and len(points):
        obj = _mesh_object(collection, members, "points", "NeuLF points", points, [], root)
        obj.hide_render = True
    elif ("points", None) in members:
        bpy.data.objects.remove(members[("points", None)])

    props = scene.neulf
    props.capture_collection, props.root = collection, root
    props.collection_name = props.root_name = ""
    props.fingerprint = description["fingerprint"]
    if first_import or scene.camera is None:  # (a re-import leaves the artist's camera, size and colours)
        # The middle camera of the rig (of the photos' most common size) becomes the active one;
        # the scene renders at its photo size.
        middle = views[convert.first_scene_camera([(v["width"], v["height"]) for v in views], centres)]["name"]
        active = _members(collection)[("camera", middle)]
        scene.camera = active
        apply_capture_camera(scene, active)
    if first_import:
        # Network outputs are sRGB: a Standard view transform shows them as the photos look.
        scene.view_settings.view_transform = "Standard"
        scene.view_settings.look = "None"
    return collection, root


# ----------------------------------------------------------------------------- Blender camera -> pinhole


def camera_request(scene, camera_obj, matrix_world=None, root_matrix=None, shift_x=None) -> dict:
    """The pinhole a Blender camera renders, in the model's COLMAP frame (`matrix_world` and
    `shift_x`: a stereo eye's, where they differ from the camera's own).

    Returns K, width, height, R, t (world-to-camera, model units) and `scale`, the root's
    uniform scale (model units x scale = Blender units)."""
    if camera_obj is None or camera_obj.type != "CAMERA":
        raise NeulfError("the scene has no active camera; add one or make a capture camera active (Ctrl+Numpad 0).")
    if root_matrix is None:
        _collection, root = find_capture(scene)
        root_matrix = root.matrix_world if root is not None else Matrix.Identity(4)
    matrix_world = camera_obj.matrix_world if matrix_world is None else matrix_world
    render = scene.render
    width, height = convert.render_size(render.resolution_x, render.resolution_y, render.resolution_percentage)
    if width < 1 or height < 1:
        raise NeulfError(f"the render size {render.resolution_x}x{render.resolution_y} at "
                         f"{render.resolution_percentage}% is {width}x{height} pixels: raise Output > Format > "
                         "Resolution %.")
    cam = camera_obj.data
    if cam.type != "PERSP":
        raise NeulfError(f"camera {camera_obj.name} is {cam.type.lower()}; NeuLF renders perspective cameras only.")
    K = convert.K_from_blender(lens=cam.lens, sensor_width=cam.sensor_width, sensor_height=cam.sensor_height,
                               sensor_fit=cam.sensor_fit, shift_x=cam.shift_x if shift_x is None else shift_x,
                               shift_y=cam.shift_y, width=width, height=height,
                               pixel_aspect_x=render.pixel_aspect_x, pixel_aspect_y=render.pixel_aspect_y)
    refuse_uneven_scale(np.array(root_matrix))
    relative = np.array(root_matrix.inverted()) @ np.array(matrix_world)
    try:
        R, t = convert.pose_from_matrix(relative)
    except ValueError as exc:
        raise NeulfError(str(exc)) from None
    return {"K": K.tolist(), "width": width, "height": height, "R": R.tolist(), "t": t.tolist(),
            "scale": convert.uniform_scale(np.array(root_matrix))}


def lens_request(camera_obj, scale: float) -> dict:
    """The camera's depth of field in model units: {} for a pinhole, else the focus distance
    (depth along the view axis) and the thin-lens aperture radius lens / (2 f-stop)."""
    dof = camera_obj.data.dof
    if not dof.use_dof or dof.aperture_fstop <= 0:
        return {}
    distance = dof.focus_distance
    if dof.focus_object is not None:
        # As Blender (BKE_camera_object_dof_distance): the object's origin, or its bone's where a
        # bone is named, along the view axis, in front of the camera or behind it.
        forward = -np.array(camera_obj.matrix_world.to_3x3().col[2])
        offset = np.array(focus_point(dof) - camera_obj.matrix_world.translation)
        distance = abs(float(offset @ forward / np.linalg.norm(forward)))
    return {"focus_distance": max(distance, 1e-5) / scale, "aperture": aperture_radius(camera_obj.data) / scale}


def aperture_radius(camera_data) -> float:
    """The thin lens's radius in Blender units, as Blender's: the focal length (mm, 1 mm =
    1e-3 units) over twice the f-stop."""
    return camera_data.lens * 1e-3 / (2.0 * camera_data.dof.aperture_fstop)


def focus_point(dof):
    """The world point a camera's focus object puts the focus on: its bone's head (posed)
    where `focus_subtarget` names one of an armature's bones, else its origin."""
    target = dof.focus_object
    bone = getattr(dof, "focus_subtarget", "")
    pose = target.pose if target.type == "ARMATURE" else None
    if bone and pose is not None and bone in pose.bones:
        return target.matrix_world @ pose.bones[bone].head
    return target.matrix_world.translation


def settings_not_followed(scene, camera_obj) -> list[str]:
    """One line for each camera or render setting an artist may have set that the light field
    does not render (it would otherwise be dropped without a word): a shaped aperture, clipping,
    motion blur."""
    notes = []
    if camera_obj is not None and camera_obj.type == "CAMERA":
        cam = camera_obj.data
        if cam.dof.use_dof and (cam.dof.aperture_blades >= 3 or abs(cam.dof.aperture_ratio - 1.0) > 1e-6):
            notes.append("the aperture's blades and ratio are not rendered: NeuLF's lens is round")
        if cam.clip_start > CLIP_START_DEFAULT + 1e-6:  # (clip end: the startup camera's 100 would warn everywhere)
            notes.append(f"{camera_obj.name}'s clip start is not rendered: the light field shows what is nearer too")
    if scene.render.use_motion_blur:
        notes.append("motion blur is not rendered by NeuLF")
    size = camera_obj.get("neulf_size") if is_capture_camera(camera_obj) else None
    if size is not None:
        render = scene.render
        if int(size[0]) * render.resolution_y != int(size[1]) * render.resolution_x:  # (another aspect ratio)
            notes.append(f"{camera_obj.name}'s photo is {int(size[0])}x{int(size[1])}; the scene renders "
                         f"{render.resolution_x}x{render.resolution_y}, another framing: Use Capture Camera renders "
                         "the photo's")
    return notes


def matrix_for_pose(root_matrix, R, t) -> Matrix:
    """A camera's world matrix for a model-frame pose, through the root."""
    return root_matrix @ _matrix(convert.matrix_from_pose(R, t))


# ----------------------------------------------------------------------------- images


def show_image(name: str, rgb: np.ndarray, *, float_buffer: bool = False, non_color: bool = False):
    """Write (H, W, 3) top-row-first values into image `name` (created or resized)."""
    height, width = rgb.shape[:2]
    image = bpy.data.images.get(name)
    if image is not None and (tuple(image.size) != (width, height) or image.is_float != float_buffer):
        bpy.data.images.remove(image)
        image = None
    if image is None:
        image = bpy.data.images.new(name, width, height, alpha=False, float_buffer=float_buffer)
    if non_color:
        image.colorspace_settings.name = "Non-Color"
    image.pixels.foreach_set(convert.image_rows_for_blender(rgb))
    image.update()
    for window in getattr(bpy.context.window_manager, "windows", []):
        for area in window.screen.areas:
            if area.type != "IMAGE_EDITOR":
                continue
            shown = area.spaces.active.image
            if shown is None or shown == image or (name.endswith("Render") and shown.name.startswith("NeuLF")):
                area.spaces.active.image = image
                area.tag_redraw()
    return image
