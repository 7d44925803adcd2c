"""Synthetic stereo scenes of steel plates with exact ground truth.

A rectified stereo pair with the ZED's WVGA geometry looks at a tilted, textured steel plate
on a darker conveyor belt; defects are heightfield pits, grooves and raised patches whose
appearance is a real NEU-DET crop (or a synthetic stand-in when NEU-DET is not available).
Both eyes are rendered by casting their own pixel rays against the scene geometry, so the
left image's ground-truth disparity ``f*B/Z`` is exact.

Modules: ``neu_crops`` (reading NEU-DET val crops), ``texture`` (procedural steel / belt /
fallback defect appearance), ``scene`` (plate + defect geometry from a seed), ``render``
(ray casting, shading, sensor nuisances), ``generate`` (sequence folders with labels).
"""
