"""`archery compare`: ARCHER and PoWER against the field's optimizers through the Gymnasium
environment of the task."""
