"""The costmap's cell values (OccupancyGrid.data, -1 unknown, 0 free .. 100 occupied): lidar
writes them (services/lidar/costmap.py), the planner steers by them and the mission warns of a
waypoint in a blocked cell. One definition, so a writer and its readers never disagree on what
"blocked" is (costmap_2d's inscribed/lethal, scaled to 0..100).
"""
from aeroperception.schemas import OccupancyGrid

UNKNOWN = OccupancyGrid.UNKNOWN
FREE = OccupancyGrid.FREE
LETHAL = OccupancyGrid.OCCUPIED     # 100: an obstacle was seen in the cell
INSCRIBED = 99                      # within the vehicle's inscribed radius of an obstacle
BLOCKED = INSCRIBED                 # cells >= this cannot be flown through (inscribed and lethal)
