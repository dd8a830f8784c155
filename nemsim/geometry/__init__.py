"""Geometry of SDF states: profile metrics (``profile``) and surface meshes (``mesh``).

Import-light: import the submodules you need.
"""
