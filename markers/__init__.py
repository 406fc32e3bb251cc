"""3D Binary Markers (3DBM): dictionaries, printable geometry (STL, PDF/SVG sheets), render meshes
and the marker set file that perception and the simulator read.

Imports only ``dockcore`` and ``calibration`` (no SAPIEN, no torch).
"""
