"""3D Binary Markers (3DBM): dictionaries, printable geometry (STL, PDF/SVG sheets), render meshes
and the marker set file that perception and the simulator read.

Imports only ``dockcore`` and ``calibration`` (no SAPIEN, no torch).
"""

if __name__ != "uwdock.markers":  # this folder reached as a top-level name (the working directory)
    raise ImportError(
        "this folder is installed as uwdock.markers: import uwdock.markers "
        "(pip install -e . from the repository puts it there)"
    )
