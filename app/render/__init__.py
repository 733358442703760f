"""Pictures of a frame: the camera, the renderers and what is drawn over them.

    camera.py    the view: eye, target, projection, framing a box
    frame.py     what every renderer shares (geometry, lights, floor, shadow) and the Renderer base
    ggui.py      the GGUI (Vulkan) back end;  software.py  the Taichi-kernel rasteriser
    factory.py   `make_renderer`: a back end by name (the base never imports its back ends)
    colors.py    per-vertex colours (body, volume, strain);  overlay.py  text, legend, palette, contact points
"""
