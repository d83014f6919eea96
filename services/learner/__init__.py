"""The learner service: learning sessions over the mesh (`service`, `session`, `rig`, `journal`),
the algorithms (`algorithms`) and the command-line tools around them (`tools`)."""
