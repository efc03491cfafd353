"""Files: CSV records, rosbag2 and MCAP reading, MCAP writing (no rclpy)."""

__all__: list = []
