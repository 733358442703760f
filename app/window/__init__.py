"""The interactive window of `main.py view` (app/commands/view.py starts it).

    viewer.py    the Viewer: scenes, the frame loop, actions, drawing, recording
    controls.py  its mouse and keys;  panel.py  its side panel and help
    picking.py   which body a click hits and how it is pushed;  orbit.py  camera moves
"""
