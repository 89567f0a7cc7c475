"""The thin ROS 2 layer around `senfunet_core`: message conversion, the node, bag tools and the CLI."""
