"""File input/output: images (NRRD/NIfTI), landmarks (Slicer .mrk.json), meshes (.vtu).

Every reader and writer works in the library's conventions: LPS millimetres, the label table of
:mod:`BreastBiomechLib.labels`.
"""
