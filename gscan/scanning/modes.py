"""The two capture modes (`gscan.scanning.capture_mode` detects them): names only, so that the command line's
choices and the scan's options read them without loading the detection."""
from __future__ import annotations

#: a static object scanned by a moving camera: the whole frame moves rigidly with the object
STATIC_OBJECT = "static-object"
#: a moving object in front of a static camera (turntable, object in hand): only its pixels are registered
MOVING_OBJECT = "moving-object"
