"""The YOLOv8 detector plugin and its dataset, training and evaluation commands (ultralytics).

ultralytics checks the network when it is imported and installs a package it misses with pip while it runs
(pi-heif, for an image Pillow cannot identify); a line's PC does neither: it runs what constraints.txt
installed. Set here, before any module of this package imports ultralytics; a user's own setting stands.
"""
import os

os.environ.setdefault("YOLO_OFFLINE", "1")
os.environ.setdefault("YOLO_AUTOINSTALL", "false")
