"""ROS: drive the machines from a ROS 1 or ROS 2 stack with OPERA's own topics, and write ROS bags.

- topics.py      the topic table (names, types, rates; namespace = machine name)
- messages.py    messages built and (de)serialised with rosbags (ROS 1 and CDR), com3_msgs/JointCmd
- sampler.py     what each output reads from the simulation, at its own rate
- controller.py  commands -> Control (latest wins, dead time, malformed messages logged once)
- bridge.py      the bridge observer + controller of a run, and the CLI's set-up (run_parts)
- transport_ros1.py   --ros1: a rospy node;  transport_tcp.py   --ros-tcp: a ROS-TCP-Endpoint client
- bag.py         output.bag: run.mcap (ROS 2, CDR) or run.bag (ROS 1)
"""
