"""Shared plumbing for every package of the toolkit: configuration dataclasses loaded from TOML,
atomic file writes, provenance records and the CLI error convention.

It sits below every other package and imports none of them (nor SAPIEN or torch).
"""

if __name__ != "uwdock.dockcore":  # this folder reached as a top-level name (the working directory)
    raise ImportError(
        "this folder is installed as uwdock.dockcore: import uwdock.dockcore "
        "(pip install -e . from the repository puts it there)"
    )
