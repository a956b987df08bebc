"""GEGL worker for ``bokehray bench``; runs under the *system* Python (GObject introspection).

Protocol: one JSON request per stdin line ``{"width", "height", "image", "radius", "out", "rmax"}``
(raw float32 files: H x W x 3 linear RGB, H x W CoC radius in px divided by rmax); answers one line
``REPLY {"ok": true, "seconds": ..., "peak_kb": ...}`` after writing H x W x 3 float32 to
``out``. Needs no numpy. Not imported by bokehray.
"""

import json
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
    print("REPLY " + json.dumps(kw), flush=True)


def main():
    try:
        import gi

        gi.require_version("Gegl", "0.4")
        from gi.repository import Gegl

        Gegl.init(None)
    except Exception as exc:  # noqa: BLE001
        reply(ok=False, error=f"GEGL not available: {exc}")
        return 1
    reply(ok=True, version=".".join(str(v) for v in Gegl.get_version()))
    for line in sys.stdin:
        try:
            req = json.loads(line)
            w, h, rmax = int(req["width"]), int(req["height"]), float(req["rmax"])
            rect = Gegl.Rectangle.new(0, 0, w, h)
            src = Gegl.Buffer.new("RGB float", 0, 0, w, h)
            with open(req["image"], "rb") as f:
                src.set(rect, "RGB float", f.read())
            # aux mask = radius / rmax (normalised by the harness); with linear-mask the blur radius
            # is mask * radius
            with open(req["radius"], "rb") as f:
                mask = f.read()
            aux = Gegl.Buffer.new("Y float", 0, 0, w, h)
            aux.set(rect, "Y float", mask)
            out = Gegl.Buffer.new("RGBA float", 0, 0, w, h)
            g = Gegl.Node()
            n_src = g.create_child("gegl:buffer-source")
            n_src.set_property("buffer", src)
            n_aux = g.create_child("gegl:buffer-source")
            n_aux.set_property("buffer", aux)
            blur = g.create_child("gegl:lens-blur")
            blur.set_property("radius", max(rmax, 0.0))
            blur.set_property("linear-mask", True)
            blur.set_property("clip", True)
            sink = g.create_child("gegl:write-buffer")
            sink.set_property("buffer", out)
            n_src.connect_to("output", blur, "input")
            n_aux.connect_to("output", blur, "aux")
            blur.connect_to("output", sink, "input")
            rss0 = reset_peak()
            t = time.perf_counter()
            sink.process()
            seconds = time.perf_counter() - t
            data = out.get(rect, 1.0, "RGB float", Gegl.AbyssPolicy.NONE)
            with open(req["out"], "wb") as f:
                f.write(bytes(data))
            reply(ok=True, seconds=seconds, peak_kb=(status_kb("VmHWM") - rss0) if rss0 is not None else None)
        except Exception as exc:  # noqa: BLE001 - reported to the harness, which skips the peer
            reply(ok=False, error=f"{type(exc).__name__}: {exc}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
