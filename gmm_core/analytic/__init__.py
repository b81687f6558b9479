"""Analytic hit and miss evidence of Gaussian mixtures over cells, without sampling (Sec. III-C, III-D).

The Monte-Carlo path (gmm_core.reconstruct) samples every component, casts a ray from the sensor
origin to each sample and counts, per cell, the rays that cross the cell (misses) and the samples
inside it (hits). This package computes the expected counts for any cell directly:

- hits (Eq. 10): N pi_k times the component's mass inside the cell. A square exactly, as a
  bivariate normal rectangle probability; a cube by quadrature over slices across the
  component's thinnest axis, each slice an exact polygon probability.
- misses (Eq. 3): N pi_k times the component's mass lying beyond the cell on rays from the
  sensor. In the isotropic frame x_I = S^-1/2 V^T (x - mu) the component is N(0, I) and rays
  stay rays (the map is affine), so the question is the standard normal mass of a region.
  2D: Eq. 5 where it is exact to 1e-10 (the cell lies well in front of the component and the
  sensor well outside it); elsewhere exactly, as the mass of the cell's wedge minus that of the
  convex hull of sensor and cell, by Brianchon-Gram (one bivariate normal orthant per corner).
  3D: well in front of the component the paper's Eq. 6-9 (the cube's shadow cast from the
  sensor onto the plane through the mean across the beam, integrated by Green's theorem with
  the erf approximation of Eq. 7; error up to 0.012 of the component's mass); near it exactly,
  as the mass of C(V) = the cone from the sensor over the cube beyond the cube's entry (a convex
  polyhedron) minus the cube's own, by the same slices as the hits.

What counts follows gmm_core.raytrace: a sample whose ray crosses the cell and ends outside it
is a miss of the cell; a sample inside the cell is a hit when it comes from the occupied mixture
and a miss when it comes from the free (max-range) mixture. The cell holding the sensor (by the
tracer's floor convention: -h <= s - c < h per axis) is crossed by every ray.

Conventions: a cell is given by its centre and side (square in 2D, cube in 3D, axis-aligned);
masses are fractions of one component (multiply by N pi_k for counts).

Modules, one job each (no names are re-exported here: the product imports evidence_2d alone):
  special      normal tail, erf differences, lower quantile, bivariate normal orthant
  polygon      standard normal mass of convex polygons, exactly (Brianchon-Gram)
  components   scan components in the world frame, the sensor's cell, cone culling
  evidence_2d  one component in one square; the grid map analytic_map_2d
  evidence_3d  one component in one cube; the paper's polygon mass by Eq. 6-9
  cells        evidence and occupancy at given cells, 2D or 3D, without a grid
"""
