"""SenFuNet engine: learned online fusion of depth sensors on sparse voxel blocks. No ROS in here."""
