"""`archery ros2`: the robot on the ROS 2 graph through rmw_zenoh's wire format, on the mesh's
own router (see README.md, "See the robot from ROS 2")."""
