"""What rotation extraction costs (fem/rotation.py), on a spinning, deforming cube.

    python -m tools.rotation_cost [--precision f32|f64] [--cells 16] [--parallel]    # from the repository's root

The cube (scenes.hard_cases.cube) turns at `spin` rad/s while it squashes, stretches and twists
(30 % and 0.5 rad at 2 Hz). For several spins and time steps this prints how often Newton
from the last step's rotation needs 1, 2, 3 or 4 steps or falls back to the SVD, and the
largest |R - polar_rotation(F)| (Frobenius); then ns per tet for the warm-started
`rotation_of`, the SVD alone (`svd_rotation`) and `polar_rotation` (SVD + Newton polish),
each also minus the cost of computing F and storing Bm R^T (what the solver does around it).
"""

import argparse
import time

import numpy as np
import taichi as ti

import fem
from fem.rotation import newton_rotation, polar_rotation, rotation_of, svd_rotation
from scenes.hard_cases import cube


def motion(X, t, spin):
    """Positions (n, 3) at time t (s): squash-stretch and twist about y at 2 Hz, turning about (1, 2, 3)."""
    phase = np.sin(2 * np.pi * 2.0 * t)
    a = np.array([1 + 0.3 * phase, 1 - 0.15 * phase, 1 - 0.15 * phase])
    twist = 0.5 * phase * X[:, 1]
    c, s = np.cos(twist), np.sin(twist)
    Y = np.column_stack([c * X[:, 0] + s * X[:, 2], X[:, 1], -s * X[:, 0] + c * X[:, 2]]) * a
    axis = np.array([1.0, 2.0, 3.0]) / np.sqrt(14)
    K = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    th = spin * t
    R = np.eye(3) + np.sin(th) * K + (1 - np.cos(th)) * K @ K
    return Y @ R.T


@ti.data_oriented
class Bench:
    def __init__(self, mesh, serial):
        m = len(mesh.tets)
        self.serial = serial
        self.tets = ti.Vector.field(4, ti.i32, m)
        self.Bm = ti.Matrix.field(3, 3, float, m)
        self.x = ti.Vector.field(3, float, len(mesh.vertices))
        self.q = ti.Vector.field(4, float, m)
        self.rotated_Bm = ti.Matrix.field(3, 3, float, m)
        self.steps_needed = ti.field(ti.i32, m)       # Newton steps from the warm start; 0: SVD
        self.error = ti.field(float, m)               # |R - R_svd_polished|_F
        X = mesh.vertices
        Dm = np.stack([X[mesh.tets[:, k]] - X[mesh.tets[:, 3]] for k in range(3)], axis=2)
        self.tets.from_numpy(mesh.tets.astype(np.int32))
        self.Bm.from_numpy(np.linalg.inv(Dm))
        self.q.from_numpy(np.tile([0.0, 0.0, 0.0, 1.0], (m, 1)))

    @ti.func
    def F(self, e):
        t = self.tets[e]
        x0, x1, x2, x3 = self.x[t[0]], self.x[t[1]], self.x[t[2]], self.x[t[3]]
        return ti.Matrix.cols([x0 - x3, x1 - x3, x2 - x3]) @ self.Bm[e]

    @ti.kernel
    def census(self):
        """steps_needed and error for this step; then q <- rotation_of (the warm start goes on)."""
        for e in self.q:
            F = self.F(e)
            needed = 0
            for k in ti.static(range(1, 5)):
                q, converged = newton_rotation(F, self.q[e], k)
                if converged and needed == 0:
                    needed = k
            self.steps_needed[e] = needed
            R, q = rotation_of(F, self.q[e])
            self.q[e] = q
            self.error[e] = (R - polar_rotation(F)).norm()

    @ti.kernel
    def f_only(self):
        ti.loop_config(serialize=self.serial)
        for e in self.q:
            self.rotated_Bm[e] = self.Bm[e] @ self.F(e).transpose()

    @ti.kernel
    def warm(self):
        ti.loop_config(serialize=self.serial)
        for e in self.q:
            R, q = rotation_of(self.F(e), self.q[e])
            self.q[e] = q
            self.rotated_Bm[e] = self.Bm[e] @ R.transpose()

    @ti.kernel
    def svd(self):
        ti.loop_config(serialize=self.serial)
        for e in self.q:
            self.rotated_Bm[e] = self.Bm[e] @ svd_rotation(self.F(e)).transpose()

    @ti.kernel
    def polar(self):
        ti.loop_config(serialize=self.serial)
        for e in self.q:
            self.rotated_Bm[e] = self.Bm[e] @ polar_rotation(self.F(e)).transpose()


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--precision", default="f32", choices=("f32", "f64"))
    parser.add_argument("--cells", type=int, default=16, help="cube of cells^3 x 6 tets")
    parser.add_argument("--parallel", action="store_true", help="all threads (default: one, ns per tet on a core)")
    args = parser.parse_args()
    fem.init("cpu", args.precision)
    mesh = cube(cells=args.cells)
    m = len(mesh.tets)
    bench = Bench(mesh, serial=not args.parallel)
    print(f"{m} tets, {args.precision}, {'all threads' if args.parallel else 'one thread'}")

    print("\nNewton steps needed from the last step's rotation (share of tet-steps), 2 s of motion")
    print(f"{'spin rad/s':>10} {'dt s':>6} {'turn/step':>9} {'1':>7} {'2':>7} {'3':>7} {'4':>7} {'SVD':>7} "
          f"{'max |R-Rp|':>10}")
    for spin, dt in [(0.0, 0.02), (10.0, 0.02), (30.0, 0.02), (10.0, 0.1), (30.0, 0.1)]:
        bench.q.from_numpy(np.tile([0.0, 0.0, 0.0, 1.0], (m, 1)))
        counts, worst = np.zeros(5), 0.0
        steps = int(round(2.0 / dt))
        for k in range(steps + 1):
            bench.x.from_numpy(motion(mesh.vertices, k * dt, spin))
            bench.census()
            if k > 0:                                   # step 0 is the cold start
                counts += np.bincount(bench.steps_needed.to_numpy(), minlength=5)
                worst = max(worst, bench.error.to_numpy().max())
        share = counts / counts.sum()
        print(f"{spin:10.0f} {dt:6.2f} {spin * dt:9.2f} " + " ".join(f"{p:7.4f}" for p in share[[1, 2, 3, 4, 0]])
              + f" {worst:10.1e}")

    print("\nns per tet (minus computing F and storing Bm R^T), spin 10 rad/s, dt 0.02 s")
    frames = [motion(mesh.vertices, k * 0.02, 10.0) for k in range(51)]
    kernels = {"F only": bench.f_only, "rotation_of, warm": bench.warm,
               "svd_rotation": bench.svd, "polar_rotation": bench.polar}
    times = {name: np.full((5, len(frames) - 1), np.inf) for name in kernels}
    for rep in range(5):             # the machine is shared: per frame, the best of five runs
        for name, kernel in kernels.items():
            bench.q.from_numpy(np.tile([0.0, 0.0, 0.0, 1.0], (m, 1)))
            bench.x.from_numpy(frames[0])
            kernel()                                     # compile, and the cold start
            for k, frame in enumerate(frames[1:]):
                bench.x.from_numpy(frame)
                ti.sync()
                start = time.perf_counter()
                kernel()
                ti.sync()
                times[name][rep, k] = time.perf_counter() - start
    costs = {name: t.min(axis=0).sum() / (len(frames) - 1) / m * 1e9 for name, t in times.items()}
    for name, ns in costs.items():
        extra = "" if name == "F only" else f"   rotation: {ns - costs['F only']:6.1f}"
        print(f"{name:>20}: {ns:6.1f}{extra}")


if __name__ == "__main__":
    main()
