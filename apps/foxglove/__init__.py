"""`archery foxglove`: a live Foxglove WebSocket server that follows one robot's mesh (see
README.md, "Watch it live in Foxglove")."""
