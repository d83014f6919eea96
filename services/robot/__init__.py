"""The robot service: the simulated iCub's joint ports, bow, arrow and target on the mesh.

`service` runs it, `handlers` serves its verbs, `simloop` is its simulation; ARCHITECTURE.md
places it among the layers and docs/names.md lists its ports and verbs.
"""
