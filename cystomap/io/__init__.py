"""Reading and writing the files the stages share: COLMAP models, registered views, meshes (PLY).

* :mod:`cystomap.io.colmap`: find and read a COLMAP model, its registered images and poses;
* :mod:`cystomap.io.views`: the registered frames of a session with their colour files;
* :mod:`cystomap.io.ply`: PLY writing (meshes, clouds) and triangle-mesh reading.
"""
