"""`archery ros2`: the robot on the ROS 2 graph through rmw_zenoh's wire format, on the mesh's
own router (see docs/ros2.md)."""
