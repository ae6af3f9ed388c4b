"""The simulated world rsucal is judged in: roads, traffic, vehicle bodies, a detector, clocks and V2X.

It imports schemas/ (and numpy, scipy, OpenCV, pyproj) but never pipeline/: the world must not share a
vehicle, camera, ground or noise model with the method it judges (docs/design.md). `simulate(preset, seed)`
returns a SimulationResult: what an RSU receives, plus the ground truth.
"""
