"""Material ids: each selects a procedural texture in shading.py and a LiDAR reflectivity."""

# ground (from the ground material raster)
ASPHALT, TILES, COBBLE, PARKING, GRASS, DIRT, GRAVEL = 1, 2, 3, 4, 5, 6, 7
# objects
FACADE, FOLIAGE, BARK, METAL, SIGN, PAINT, GLASS, TYRE, CLOTH, SKIN = 10, 11, 12, 13, 14, 15, 16, 17, 18, 19
CONCRETE, CONE, PLASTIC, BUS_BODY, CARGO, HAZARD, STRIPES, FENCE, LAMP = 20, 21, 22, 23, 24, 25, 26, 27, 28

# LiDAR intensity scale (nuScenes intensities are 0..255; retro-reflective paint and signs are high)
REFLECTIVITY = {
    ASPHALT: 8, TILES: 20, COBBLE: 14, PARKING: 10, GRASS: 12, DIRT: 10, GRAVEL: 16,
    FACADE: 25, FOLIAGE: 12, BARK: 8, METAL: 35, SIGN: 200, PAINT: 30, GLASS: 6, TYRE: 4,
    CLOTH: 15, SKIN: 18, CONCRETE: 28, CONE: 120, PLASTIC: 20, BUS_BODY: 30, CARGO: 30,
    HAZARD: 90, STRIPES: 150, FENCE: 20, LAMP: 60,
}
PAINT_REFLECTIVITY = 90  # lane markings
