"""Session-wide test set-up: an own ROS_DOMAIN_ID, loopback-only discovery, ament index."""
import os
import sys

# Each test session gets its own DDS domain (0..101 are safe on Linux) so parallel runs on
# one machine never see each other's nodes; discovery stays on loopback.
os.environ.setdefault('ROS_DOMAIN_ID', str(1 + os.getpid() % 100))
os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
os.environ.setdefault('AMENT_PREFIX_PATH', sys.prefix)
os.environ.setdefault('MPLBACKEND', 'Agg')
sys.path.insert(0, os.path.dirname(__file__))
