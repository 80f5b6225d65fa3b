"""Surveying a facility from walk-through footage (``companion survey``, ``companion map check``).

observations.py  the detection phase: frames -> sightings (points against pixels), keyframes
graph.py         markers seen together, groups, first poses grown out from the anchors
adjust.py        bundle adjustment (scipy least_squares, sparse Jacobian, Huber loss), covariances
survey.py        the whole survey: anchors, agreement of several anchors, outliers, the map
check.py         map check: each marker's pose from the others against its map entry
report.py        survey.json and survey.png (top view with uncertainty ellipses and the camera path)
"""
