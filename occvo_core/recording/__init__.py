"""ROS 2 recordings (MCAP files and bag folders, CDR) written and read with rosbags, no ROS install: the message
builders and decoders, the writer (bag versions per distribution, QoS), the nuScenes drive converter."""
