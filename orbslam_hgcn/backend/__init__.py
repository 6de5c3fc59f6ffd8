"""Optimisation back end (the package's only gtsam user): pose-only refinement, local,
global and two-view bundle adjustment, Sim(3) essential-graph optimisation, the refinement
of a loop's Sim(3) from its matches. Every function takes and returns arrays; import the
submodules (gtsam loads with bundle_adjustment, pose_graph and sim3_refine only)."""
