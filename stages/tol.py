"""One place for the numeric tolerances shared by the stages (metres, radians)."""

#: Two points closer than this are the same point (m).
merge = 1e-6
#: Two unit normals whose dot product exceeds ``1 - planar`` are coplanar.
planar = 1e-6
#: Zero for lengths and areas (m, m^2).
zero = 1e-12
