"""Optimisation back end (the package's only gtsam user): pose-only refinement, local,
global and two-view bundle adjustment, Sim(3) essential-graph optimisation. Every function
takes and returns arrays; import the submodules (gtsam loads with bundle_adjustment and
pose_graph only)."""
