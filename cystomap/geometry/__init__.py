"""Geometry every stage shares.

* :mod:`cystomap.geometry.sim3`: similarity transforms and the Umeyama least-squares fit;
* :mod:`cystomap.geometry.raycast`: ray casting and distances on a triangle mesh (open3d);
* :mod:`cystomap.geometry.trimesh`: triangle-mesh measures (areas, volume, normals, topology);
* :mod:`cystomap.geometry.quadric`: robust sphere and ellipsoid fits;
* :mod:`cystomap.geometry.sphere`: the icosphere grid and functions on the unit sphere;
* :mod:`cystomap.geometry.pointcloud`: point-cloud filters (statistical outliers, voxel binning).
"""
