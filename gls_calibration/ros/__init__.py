"""The ROS machinery shared by the nodes: parameters, calls with deadlines, message conversion, diagnostics, RViz."""
