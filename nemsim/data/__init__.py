"""Dataset I/O: HDF5 trajectory files (``hdf5``), streaming torch datasets (``dataset``), split manifests
(``splits``). Import the submodules directly; nothing heavy is imported here.
"""
