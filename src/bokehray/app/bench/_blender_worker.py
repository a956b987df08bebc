"""Blender worker for ``bokehray bench``; runs under a Python that has ``bpy`` (PyPI).

Protocol as in ``_gegl_worker.py``. The compositor graph is Image -> Defocus(Image, Z) ->
Composite, with the CoC radius map as Z: ``use_zbuffer`` off makes the node read Z as a radius
(``radius = Z * z_scale``), so Z = r / rmax and ``z_scale = rmax``. No gamma correction, no
threshold, no preview (full quality), disc bokeh. The empty 3D scene is rendered by the
Workbench engine; the composite is written as a 32-bit float EXR (linear, no view transform)
and read back with bpy. Not imported by bokehray.
"""

import json
import os
import re
import sys
import time


def status_kb(field):
    try:
        with open("/proc/self/status") as f:
            m = re.search(r"^" + field + r":\s*(\d+) kB", f.read(), re.M)
        return int(m.group(1)) if m else 0
    except OSError:
        return 0


def reset_peak():
    """Reset VmHWM to the current RSS, so the next peak is this render's; returns the RSS (kB)."""
    try:
        with open("/proc/self/clear_refs", "w") as f:
            f.write("5")
    except OSError:
        return None
    return status_kb("VmRSS")


def reply(**kw):
    sys.stdout.flush()
    print("REPLY " + json.dumps(kw), flush=True)


def main():
    try:
        import bpy
        import numpy as np
    except Exception as exc:  # noqa: BLE001
        reply(ok=False, error=f"bpy not available: {exc}")
        return 1
    sc = bpy.context.scene
    for o in list(bpy.data.objects):
        bpy.data.objects.remove(o)
    sc.render.engine = "BLENDER_WORKBENCH"
    sc.render.resolution_percentage = 100
    sc.render.image_settings.file_format = "OPEN_EXR"
    sc.render.image_settings.color_depth = "32"
    sc.view_settings.view_transform = "Standard"
    sc.render.use_compositing = True
    sc.use_nodes = True
    tree = sc.node_tree
    for n in list(tree.nodes):
        tree.nodes.remove(n)
    n_img = tree.nodes.new("CompositorNodeImage")
    n_z = tree.nodes.new("CompositorNodeImage")
    defocus = tree.nodes.new("CompositorNodeDefocus")
    defocus.bokeh = "CIRCLE"
    defocus.use_zbuffer = False
    defocus.use_gamma_correction = False
    defocus.use_preview = False
    defocus.threshold = 0.0
    comp = tree.nodes.new("CompositorNodeComposite")
    tree.links.new(n_img.outputs[0], defocus.inputs[0])
    tree.links.new(n_z.outputs[0], defocus.inputs[1])
    tree.links.new(defocus.outputs[0], comp.inputs[0])
    reply(ok=True, version=bpy.app.version_string)

    def image(name, w, h):
        im = bpy.data.images.get(name)
        if im is None or tuple(im.size) != (w, h):
            if im is not None:
                bpy.data.images.remove(im)
            im = bpy.data.images.new(name, w, h, float_buffer=True, alpha=True)
            im.colorspace_settings.name = "Non-Color"  # data: no colour conversion on the way in
        return im

    for line in sys.stdin:
        try:
            req = json.loads(line)
            w, h, rmax = int(req["width"]), int(req["height"]), float(req["rmax"])
            rgb = np.fromfile(req["image"], np.float32).reshape(h, w, 3)
            rad = np.fromfile(req["radius"], np.float32).reshape(h, w)
            rgba = np.ones((h, w, 4), np.float32)
            rgba[..., :3] = rgb
            z = np.ones((h, w, 4), np.float32)
            z[..., :3] = rad[..., None]  # radius / rmax, normalised by the harness
            n_img.image = image("bokehray_in", w, h)
            n_img.image.pixels.foreach_set(rgba[::-1].ravel())  # Blender rows go bottom-up
            n_z.image = image("bokehray_z", w, h)
            n_z.image.pixels.foreach_set(z[::-1].ravel())
            defocus.z_scale = max(rmax, 0.0)
            defocus.blur_max = max(rmax + 1.0, 1.0)
            sc.render.resolution_x, sc.render.resolution_y = w, h
            path = os.path.abspath("out.exr")
            sc.render.filepath = path
            rss0 = reset_peak()
            t = time.perf_counter()
            bpy.ops.render.render(write_still=True)
            seconds = time.perf_counter() - t
            res = bpy.data.images.load(path, check_existing=False)
            a = np.empty(w * h * 4, np.float32)
            res.pixels.foreach_get(a)
            bpy.data.images.remove(res)
            a.reshape(h, w, 4)[::-1, :, :3].astype(np.float32).tofile(req["out"])
            reply(ok=True, seconds=seconds, peak_kb=(status_kb("VmHWM") - rss0) if rss0 is not None else None)
        except Exception as exc:  # noqa: BLE001 - reported to the harness, which skips the peer
            reply(ok=False, error=f"{type(exc).__name__}: {exc}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
