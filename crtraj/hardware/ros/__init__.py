"""The ROS 2 bridge (optional extra ``[ros]``): options, message checks, the node and the loop's device port."""
