"""Geometry of SDF states: profile metrics (``profile``), surface meshes (``mesh``) and the frame of
reference of both (``frame``).

Import-light: import the submodules you need.
"""
