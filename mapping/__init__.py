"""The neural implicit map: equivariant encoder, invariant decoder, sparse voxel map, remapping.

``mapping`` knows nothing about sensors: it takes points with normals in a frame, and poses.
"""
