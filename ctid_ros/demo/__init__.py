"""``make demo``: a wheel drive identified live on ROS 2, recorded, replayed and plotted."""

__all__: list = []
