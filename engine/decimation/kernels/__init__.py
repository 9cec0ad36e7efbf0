"""Warp kernels of the parallel, topology-preserving quadric-error edge collapse (host loop:
``engine.decimation.passes``), by concern: ``quadrics``, ``costs``, ``guards``, ``claims``, ``collapse``; and those
of decimating a mesh piece by piece (``tiles``) and of vertex clustering (``cluster``). No host logic lives here.

The mesh lives on the device as ``pos`` (V) ``vec3`` (z, y, x) mm and ``faces`` (F) ``vec3i``; a collapsed face is
marked ``(-1, -1, -1)`` and a collapsed vertex ``DEAD``. One pass:

1. incidence: every vertex's *star* (the faces around it) as CSR, counted, scanned, filled and sorted per vertex
   (``engine.surface.kernels.topology``; sorted so that every later sum runs in a fixed order: the result is
   deterministic);
2. ``costs.edge_costs``: every collapsible edge (once, from its half-edge ``a < b``) gets its Garland-Heckbert cost
   and its new position, as a 31-bit cost code (monotonic in the cost) or ``NO_KEY``; a histogram of the codes
   gives the host the cost quantile under which edges compete, and ``guards.check_candidates`` runs every guard
   (link condition, valences, face flips, degenerate faces) on those only;
3. ``claims``: each competing edge does an atomic min of its key ``(cost code << 32) | mix32(edge slot)`` onto every
   face of its two stars and wins only where it holds all of them (a few rounds; winners take their faces for the
   rest of the pass). Winners' stars are face-disjoint, so their collapses and guards are independent;
4. ``collapse.apply_collapses`` moves the survivor, adds the quadrics (``Q_s += Q_r``) and rewrites the removed
   vertex's star.

Quadrics are float64, taken about a local origin (the mesh's centre) so that they do not cancel at scan scale.
"""
