"""Plumbing every floor may use: where the shipped models and scenarios are (`assets`),
files written whole or not at all (`files`), code versions and checksums (`provenance`),
modules loaded on first use (`lazy`) and the LLVM load order (`native`).

Floor 1 of the package: imports nothing of drake_grasp but its version.
"""
