"""`archery yarp`: the robot of a running mesh as a YARP robot (YARP 3.5's wire, through YARP's
own library): the parts as iCub's simulator serves them to `remote_controlboard`, the target
camera as an image port, the detector's rewards and the world's events as bottles, and the
archery verbs on a text RPC port."""
