"""Topic tools, the `yarp` CLI of this mesh: ports, alive, read, write, rpc, view, interface, hz,
record, replay, selfcheck."""
