"""The runtime of the mesh: the Zenoh node (publish, subscribe, RPC server and client, liveliness
and instances), the services' shape (`service_main`, config flags), the job queue, logging, the
router and secure mode (credentials, access control). It imports `protocol` and nothing else of
ours."""
