"""Preferences: which Python runs neulf_core (torch, pycolmap), one-click install, device."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import bpy
from bpy.props import EnumProperty, StringProperty

from . import core, jobs, tasks

ADDON = __package__.rpartition(".")[0]   # the extension's module, e.g. bl_ext.user_default.neulf
PACKAGES = ["torch", "pycolmap==4.2.1", "pillow", "av"]
TORCH_INDEX = {"CPU": "https://download.pytorch.org/whl/cpu", "CUDA": "https://download.pytorch.org/whl/cu128"}


def deps_dir(create: bool = False) -> Path:
    """The extension's own folder for installed packages (survives upgrades)."""
    try:
        return Path(bpy.utils.extension_path_user(ADDON, path="deps", create=create))
    except ValueError:  # not loaded as an extension (imported through sys.path)
        path = Path(bpy.utils.user_resource("DATAFILES", path="neulf")) / "deps"
        if create:
            path.mkdir(parents=True, exist_ok=True)
        return path


def get_prefs(context=None):
    context = context or bpy.context
    addon = context.preferences.addons.get(ADDON)
    return addon.preferences if addon is not None else None


def worker_python(prefs=None) -> tuple[str, list[str]]:
    """(interpreter, extra sys.path entries) the worker and training run with."""
    chosen = bpy.path.abspath(prefs.python_path) if prefs is not None and prefs.python_path.strip() else ""
    if chosen:
        return chosen, []
    deps = deps_dir()
    return sys.executable, [str(deps)] if deps.is_dir() else []


def get_core(context=None) -> core.Core:
    prefs = get_prefs(context)
    python, extra = worker_python(prefs)
    device = None if prefs is None or prefs.device == "AUTO" else prefs.device.lower()
    mode = "AUTO" if prefs is None else prefs.render_mode
    if prefs is not None and prefs.python_path.strip():
        mode = "WORKER" if mode == "AUTO" else mode  # a chosen interpreter is used for everything
    return core.Core(python, extra, device, mode)


def _on_change(self, _context):
    core.shutdown()


def _on_python_change(self, context):
    """Another interpreter: the last Check's verdict was about the one before."""
    _on_change(self, context)
    self.status = NOT_CHECKED


NOT_CHECKED = "not checked yet: click Check"


class NeulfPreferences(bpy.types.AddonPreferences):
    bl_idname = ADDON

    python_path: StringProperty(
        name="Python with torch", subtype="FILE_PATH", update=_on_python_change,
        description="A Python interpreter that has torch, pycolmap, Pillow and av (e.g. a conda env). "
                    "Empty: Blender's Python with the packages installed below")
    device: EnumProperty(name="Device", update=_on_change, items=[
        ("AUTO", "Automatic", "CUDA, then Apple MPS, then CPU"), ("CUDA", "CUDA", "NVIDIA GPU"),
        ("MPS", "MPS", "Apple GPU"), ("CPU", "CPU", "Processor")])
    render_mode: EnumProperty(name="Render In", update=_on_change, items=[
        ("AUTO", "Automatic", "In Blender when torch imports there, else in the worker process"),
        ("WORKER", "Worker Process", "Always in a separate process (a crash never takes Blender down)")])
    torch_variant: EnumProperty(name="Torch Build", items=[
        ("DEFAULT", "Default", "pip's default torch for this system"),
        ("CPU", "CPU Only", "Smaller download; no GPU"), ("CUDA", "CUDA 12.8", "NVIDIA GPUs")])
    status: StringProperty(name="Status", default=NOT_CHECKED)

    def draw(self, context):
        layout = self.layout
        layout.prop(self, "python_path")
        row = layout.row()
        row.prop(self, "device")
        row.prop(self, "render_mode")
        box = layout.box()
        install = tasks.get("install") or tasks.get("check")
        if install is not None and install.running:
            box.progress(factor=install.state["fraction"], type="BAR", text=install.state["message"][:80])
        box.label(text=self.status, icon="INFO")
        row = box.row()
        row.operator("neulf.check_dependencies", icon="FILE_REFRESH")
        sub = row.row()
        sub.enabled = not self.python_path.strip()
        sub.prop(self, "torch_variant", text="")
        sub.operator("neulf.install_dependencies", icon="IMPORT")
        if not bpy.app.online_access:
            box.label(text="Online access is off (Preferences > System > Network): installing is disabled.",
                      icon="ERROR")
        box.label(text=f"Packages folder: {deps_dir()}")


def _describe(job, where: str) -> str:
    if job.state["status"] != "finished":
        return f"not usable: {job.state.get('error') or job.state['status']} ({where})"
    try:
        info = json.loads(job.lines[-1])
    except (IndexError, json.JSONDecodeError):
        return f"not usable: unexpected answer from {where}"
    return (f"torch {info['torch']}, pycolmap {info['pycolmap']} in Python {info['python_version']} "
            f"({where}); device: {info['device_name']}")


class NEULF_OT_check_dependencies(bpy.types.Operator):
    """Check that the NeuLF Python imports torch, pycolmap, Pillow and av, and which device it will use"""

    bl_idname = "neulf.check_dependencies"
    bl_label = "Check"

    def execute(self, context):
        prefs = get_prefs(context)
        python, extra = worker_python(prefs)
        core.shutdown()
        try:
            job = jobs.python_check_job(python, jobs.core_environment(extra))
        except Exception as exc:
            if prefs is not None:
                prefs.status = f"not usable: {exc}"
            self.report({"ERROR"}, str(exc))
            return {"CANCELLED"}

        def done(job):
            text = _describe(job, python)
            if prefs is not None:
                prefs.status = text

        tasks.start("check", job, done)
        if bpy.app.background:
            job.wait(timeout=300)
            tasks.poll_all()
            self.report({"INFO"}, prefs.status if prefs else _describe(job, python))
        return {"FINISHED"}


class NEULF_OT_install_dependencies(bpy.types.Operator):
    """Download and install torch, pycolmap, pillow and av into the extension's own folder"""

    bl_idname = "neulf.install_dependencies"
    bl_label = "Install Dependencies"

    @classmethod
    def poll(cls, context):
        return not tasks.running("install")

    def execute(self, context):
        if not bpy.app.online_access:
            self.report({"ERROR"}, "Online access is disabled (Preferences > System > Network); "
                                   "enable it to install torch, pycolmap, Pillow and av, or choose a Python that has them.")
            return {"CANCELLED"}
        prefs = get_prefs(context)
        target = deps_dir(create=True)
        variant = prefs.torch_variant if prefs is not None else "DEFAULT"
        job = jobs.pip_install_job(sys.executable, str(target), PACKAGES, TORCH_INDEX.get(variant))

        def done(job):
            if job.state["status"] == "finished":
                if prefs is not None:
                    prefs.status = "installed; checking ..."
                bpy.ops.neulf.check_dependencies()
            elif prefs is not None:
                prefs.status = f"install failed: {job.state['error']}"

        tasks.start("install", job, done)
        if bpy.app.background:
            job.wait()
            tasks.poll_all()
            if job.state["status"] != "finished":
                self.report({"ERROR"}, f"install failed: {job.state['error']}")
                return {"CANCELLED"}
        else:
            self.report({"INFO"}, f"installing torch, pycolmap, Pillow and av into {target} (several minutes)")
        return {"FINISHED"}


CLASSES = (NeulfPreferences, NEULF_OT_check_dependencies, NEULF_OT_install_dependencies)
