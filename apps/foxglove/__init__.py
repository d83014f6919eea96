"""`archery foxglove`: a live Foxglove WebSocket server that follows one robot's mesh (see
docs/foxglove.md)."""
