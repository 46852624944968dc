"""
Road vehicle additions (not in the papers).

The ground plane of the features, the direct road alignment and the rolling-vehicle prior; all
off by default (config/road_vehicle.yaml).
"""
