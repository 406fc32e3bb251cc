"""Shared plumbing for every package of the toolkit: configuration dataclasses loaded from TOML,
atomic file writes, provenance records and the CLI error convention.

It sits below every other package and imports none of them (nor SAPIEN or torch).
"""
