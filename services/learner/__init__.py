"""The learner service: learning sessions over the mesh (`service`, `session`, `rig`, `journal`)
and the algorithms (`algorithms`)."""
