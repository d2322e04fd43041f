"""3D transfer: head pose from 2D landmarks and Laplacian deformation of a face mesh.

Modules: :mod:`~facesynth.mesh.camera` (conventions), :mod:`~facesynth.mesh.pose`
(DLT, normalised DLT, K/R/C, solver dispatch), :mod:`~facesynth.mesh.epnp`,
:mod:`~facesynth.mesh.io` (meshes, landmark maps), :mod:`~facesynth.mesh.laplacian`,
:mod:`~facesynth.mesh.deform`, :mod:`~facesynth.mesh.transfer`,
:mod:`~facesynth.mesh.render`, :mod:`~facesynth.mesh.smoothing`, :mod:`~facesynth.mesh.cli`.
Face scans -> parametric coordinates for geometry videos: :mod:`~facesynth.mesh.holes` (hole
filling), :mod:`~facesynth.mesh.segment` (geodesic segmentation), :mod:`~facesynth.mesh.eip`
(expression-invariant parameterisation and its domain),
:mod:`~facesynth.mesh.paths` (edge paths, geodesics), :mod:`~facesynth.mesh.scan` (the
per-frame pipeline), :mod:`~facesynth.mesh.synthetic` (a synthetic scan for tests).
"""
