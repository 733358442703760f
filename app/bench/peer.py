"""The peer's side of the benchmark's contact comparison: the same boxes stepped by Newton's VBD
(Vertex Block Descent, with self-contact, as in its softbody_gift example), in a Python that has
`newton` (it is not this project's dependency: `pip install newton` in a virtual environment of
its own). app/bench/contact.py writes the boxes and runs, from this repository's root,

    PEER_PYTHON -m app.bench.peer IN.npz OUT.npz

IN.npz: vertices (n, 3) m and tets (m, 4) of every box, body (n,) each vertex's box, the scene's
settings and the peer's contact stiffness (see `SETTINGS`). Prints one JSON line, {"ms": [wall ms
of each timed step], "newton", "warp", "device", "substeps", "iterations", "particle_radius"}, and
writes OUT.npz: positions (steps, n, 3) m after each timed step, which app/bench/contact.py measures
as it measures ours.

What VBD cannot take as we give it (app/bench/contact_report.py says so beside the numbers): its
elasticity is neo-Hookean with our E and nu's Lame parameters (ours: corotational); its damping is
the stiffness part of ours only (k_damp = beta; alpha, the mass part, has no counterpart); its
contact is a penalty of the stiffness IN.npz gives (N/m, between boxes closer than the contact
distance and with the ground), not a barrier; its ground friction is sqrt(mu_contact mu_shape), so
the ground's mu is set to give ours.
"""

import json
import sys
import time

import numpy as np

SETTINGS = ("dt", "warmup", "steps", "E", "nu", "density", "beta", "gravity", "ground", "ground_friction",
            "distance", "friction", "contact_stiffness")
SUBSTEPS = 10          # VBD sub-steps of a step: the softbody_gift example's; its self-contact truncates each
                       # vertex's move between detections to about half the detection reach, so one
                       # 0.02 s sub-step would hold a box falling at 4 m/s to a fraction of that speed
ITERATIONS = 15        # VBD iterations a sub-step, the softbody_gift example's
CONTACT_DAMPING = 0.5     # the softbody_gift example's
PARTICLE_RADIUS = 1e-3    # m: a vertex touches the ground this far above it (ours: at the ground)


def lame(E, nu):
    """(mu, lambda), Pa: the Lame parameters of Young's modulus E and Poisson's ratio nu."""
    return E / (2 * (1 + nu)), E * nu / ((1 + nu) * (1 - 2 * nu))


def positive(vertices, tets):
    """tets with two corners swapped where their volume is negative (Newton skips those as inverted)."""
    x = vertices[tets]
    volume = np.einsum("ij,ij->i", x[:, 1] - x[:, 0], np.cross(x[:, 2] - x[:, 0], x[:, 3] - x[:, 0]))
    tets = tets.copy()
    tets[volume < 0, 1], tets[volume < 0, 2] = tets[volume < 0, 2], tets[volume < 0, 1].copy()
    return tets


def build(data):
    """(model, solver, collision pipeline, settings) of the boxes in `data` (IN.npz's arrays)."""
    import newton
    import warp as wp

    s = {key: data[key].item() if data[key].ndim == 0 else data[key] for key in SETTINGS}
    builder = newton.ModelBuilder(up_axis=newton.Axis.Y, gravity=tuple(map(float, s["gravity"])))
    # Newton mixes the ground's friction with the contacts' as sqrt(mu_contact mu_shape)
    builder.add_ground_plane(height=float(s["ground"]), cfg=newton.ModelBuilder.ShapeConfig(
        mu=s["ground_friction"] ** 2 / s["friction"]))
    mu, lam = lame(s["E"], s["nu"])
    vertices, tets, body = data["vertices"], data["tets"], data["body"]
    for b in range(body.max() + 1):
        ids = np.flatnonzero(body == b)
        local = np.searchsorted(ids, tets[np.isin(tets[:, 0], ids)])
        builder.add_soft_mesh(pos=wp.vec3(0.0), rot=wp.quat_identity(), scale=1.0, vel=wp.vec3(0.0),
                              vertices=[tuple(map(float, v)) for v in vertices[ids]],
                              indices=positive(vertices[ids], local).flatten().tolist(), density=float(s["density"]),
                              k_mu=mu, k_lambda=lam, k_damp=float(s["beta"]), particle_radius=PARTICLE_RADIUS)
    builder.color()
    model = builder.finalize()
    model.soft_contact_ke, model.soft_contact_kd = float(s["contact_stiffness"]), CONTACT_DAMPING
    model.soft_contact_mu = float(s["friction"])
    solver = newton.solvers.SolverVBD(model, iterations=ITERATIONS, particle_enable_self_contact=True,
                                      particle_self_contact_margin=float(s["distance"]),
                                      particle_self_contact_gap=float(s["distance"]),
                                      particle_topological_contact_filter_threshold=1,
                                      particle_enable_tile_solve=False)
    return model, solver, newton.CollisionPipeline(model), s


def run(data):
    """(JSON-able results, positions (steps, n, 3)): `warmup` steps from the start, then `steps` timed."""
    import newton
    import warp as wp

    model, solver, pipeline, s = build(data)
    state, spare, control = model.state(), model.state(), model.control()
    contacts = pipeline.contacts()
    dt = float(s["dt"]) / SUBSTEPS

    def step():
        nonlocal state, spare
        for _ in range(SUBSTEPS):
            state.clear_forces()
            pipeline.collide(state, contacts)
            solver.step(state, spare, control, contacts, dt)
            state, spare = spare, state
        wp.synchronize()

    for _ in range(int(s["warmup"])):
        step()
    ms, positions = [], []
    for _ in range(int(s["steps"])):
        start = time.perf_counter()
        step()
        ms.append(1e3 * (time.perf_counter() - start))
        positions.append(state.particle_q.numpy().astype(np.float64))
    info = {"ms": ms, "newton": newton.__version__, "warp": wp.config.version, "device": str(wp.get_device()),
            "substeps": SUBSTEPS, "iterations": ITERATIONS, "particle_radius": PARTICLE_RADIUS}
    return info, np.array(positions)


if __name__ == "__main__":
    source, target = sys.argv[1:3]
    info, positions = run(dict(np.load(source)))
    np.savez(target, positions=positions)
    print(json.dumps(info))
