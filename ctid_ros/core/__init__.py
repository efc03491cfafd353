"""
The numerical core: model language, exact simulation, data, excitation and a simulated plant.

Nothing here imports ROS or depends on another layer of the package.
"""
