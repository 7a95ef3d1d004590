"""A reference elastic calibration of DLR Agile Justin, written outside the product (plain numpy + scipy
least_squares, guessed lumped masses), to learn what the data can give and what the product's chain model misses.

It is not the product: it measures which structure matters. Finding (docs/RESULTS.md 3.5): the other arm's
weight bending the torso is most of what a per-arm chain cannot see (issue 11's trees carry it).

Models
  A  per-arm chain, geometric only
  B  per-arm chain, geometric + joint compliance (gravity from torso + that arm only)
  C  tree (torso shared, both arms), geometric + joint compliance, torso torques from both arms
  D  C + lateral compliance (2 extra rotational compliances per joint)
  B2 control: per-arm chain, but the other arm's mass also loads the torso
  C0 control: tree without the arms' masses on the torso;  E control: tree, geometric only
Splits as benchmarks/real_diagnosis.py (permutation default_rng(1000 + s), 350 train / 150 test).
Run:  .venv/bin/python -m benchmarks.justin_reference [--splits 0 1 2] [--models A B C D]
"""
import os, sys, time, json, argparse
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
import numpy as np
import yaml
from scipy.optimize import least_squares

from calib_core.datasets import JUSTIN_DIR, SHARED_DATASETS  # noqa: E402

D = SHARED_DATASETS / JUSTIN_DIR
Y = yaml.safe_load(open(f"{D}/justin19_nominal.yaml"))
data = np.loadtxt(f"{D}/measurements_flat.csv", delimiter=",", skiprows=1)
Q = data[:, 1:20]
MEAS = {"right": data[:, 20:23], "left": data[:, 23:26]}
NP = len(Q)


def orth(T):
    T = np.array(T, float)
    U, _, Vt = np.linalg.svd(T[:3, :3])
    R = U @ Vt
    if np.linalg.det(R) < 0:
        R = U @ np.diag([1, 1, -1]) @ Vt
    T[:3, :3] = R
    return T


DH = {"torso": np.array(Y["DH_TORSO"], float), "right": np.array(Y["DH_RIGHT"], float),
      "left": np.array(Y["DH_LEFT"], float)}
F_TORSO = np.array(Y["F_TORSO_BASE"], float)
F_BASE = {"right": orth(Y["F_RIGHT_BASE"]), "left": orth(Y["F_LEFT_BASE"])}
F_TCP = np.array(Y["F_TCP"], float)
T_C0 = np.array([[0, -1, 0, -2.5], [1, 0, 0, 2.0], [0, 0, 1, 0.1], [0, 0, 0, 1]], float)
MARK0 = {"right": np.array([-0.1, -0.03, 0.1]), "left": np.array([-0.1, 0.03, 0.05])}
JIDX = {"right": np.arange(3, 10), "left": np.arange(10, 17)}
G = np.array([0, 0, -9.81])

# ---- lumped masses (kg) and COM (in link frame after Rz(q)Tz(d)) ----
# torso: link0 (pan) 5 kg on axis, link1/2 8 kg mid-link, link3 (upper torso + head) 15 kg
TORSO_M = [(5.0, [0, 0, 0]), (8.0, [0.15, 0, 0]), (8.0, [0.15, 0, 0]), (15.0, [0.15, 0.05, 0.0])]
ARM_LINK_M = 2.0    # each of 7 arm links, COM at middle of the d-segment of the link
HAND_M = 2.0        # at TCP
# optional mass variant for sensitivity checks: JUSTIN_MASS="upper_torso,arm_link,hand"
if os.environ.get("JUSTIN_MASS"):
    _ut, ARM_LINK_M, HAND_M = map(float, os.environ["JUSTIN_MASS"].split(","))
    TORSO_M[3] = (_ut, TORSO_M[3][1])


def Rx(a):
    c, s = np.cos(a), np.sin(a)
    return np.array([[1, 0, 0, 0], [0, c, -s, 0], [0, s, c, 0], [0, 0, 0, 1.]])


def Tr(x, y, z):
    T = np.eye(4); T[:3, 3] = [x, y, z]; return T


def rodrigues(v):
    """v (...,3) -> R (...,3,3)"""
    v = np.asarray(v, float)
    th = np.linalg.norm(v, axis=-1)[..., None, None]
    K = np.zeros(v.shape[:-1] + (3, 3))
    K[..., 0, 1], K[..., 0, 2], K[..., 1, 2] = -v[..., 2], v[..., 1], -v[..., 0]
    K[..., 1, 0], K[..., 2, 0], K[..., 2, 1] = v[..., 2], -v[..., 1], v[..., 0]
    small = th < 1e-9
    ths = np.where(small, 1.0, th)
    A = np.where(small, 1.0, np.sin(ths) / ths)
    B = np.where(small, 0.5, (1 - np.cos(ths)) / ths ** 2)
    return np.eye(3) + A * K + B * (K @ K)


def pert(p6):
    """p6 = [dx,dy,dz (mm), rx,ry,rz (mrad)] -> 4x4"""
    T = np.eye(4)
    T[:3, :3] = rodrigues(np.asarray(p6[3:]) * 1e-3)
    T[:3, 3] = np.asarray(p6[:3]) * 1e-3
    return T


def RzTz(th, d):
    n = th.shape[0]
    c, s = np.cos(th), np.sin(th)
    M = np.zeros((n, 4, 4))
    M[:, 0, 0], M[:, 0, 1], M[:, 1, 0], M[:, 1, 1] = c, -s, s, c
    M[:, 2, 2] = 1; M[:, 3, 3] = 1; M[:, 2, 3] = d
    return M


def rot4(v):
    n = v.shape[0]
    M = np.zeros((n, 4, 4)); M[:, :3, :3] = rodrigues(v); M[:, 3, 3] = 1
    return M


class Model:
    """arms: tuple of arm names fitted jointly (tree if 2).
    compl: 'none' | 'joint' | 'lateral'.
    load_arms: which arms' masses load the torso joints."""

    def __init__(self, arms, compl="none", load_arms=None, lam=0.01, lam_c=1e-4):
        self.arms = tuple(arms)
        self.compl = compl
        self.load_arms = tuple(load_arms if load_arms is not None else arms)
        self.lam, self.lam_c = lam, lam_c
        self.kc = {"none": 0, "joint": 1, "lateral": 3}[compl]
        # layout
        sl = {}; k = 0
        def add(name, n):
            nonlocal k; sl[name] = slice(k, k + n); k += n
        add("cam", 6)
        add("pt", 4 * 6)
        for a in self.arms:
            add("p_" + a, 7 * 6)
        for a in self.arms:
            add("m_" + a, 3)
        if self.kc:
            add("ct", 4 * self.kc)
            for a in self.arms:
                add("c_" + a, 7 * self.kc)
        self.sl, self.n = sl, k
        self.ridge = np.zeros(k)
        self.ridge[sl["pt"]] = lam
        for a in self.arms:
            self.ridge[sl["p_" + a]] = lam
        if self.kc:
            self.ridge[sl["ct"]] = lam_c
            for a in self.arms:
                self.ridge[sl["c_" + a]] = lam_c
        self.ridge_idx = np.nonzero(self.ridge)[0]

    # ---------------------------------------------------------------
    def _chain(self, T0, dh, qs, P, defl=None):
        """walk a chain. T0 (n,4,4) or (4,4). returns list of (Tpre, Rot_after_Rz, Tlink)."""
        out = []
        T = T0
        for i in range(len(dh)):
            d, th, a, al = dh[i]
            Tpre = T @ (Rx(al) @ Tr(a, 0, 0) @ P[i])
            if Tpre.ndim == 2:
                Tpre = np.broadcast_to(Tpre, (qs.shape[0], 4, 4))
            qq = qs[:, i]
            if defl is not None:
                qq = qq + defl[i][:, 2]
            J = RzTz(th + qq, 0.0)
            Tz = Tr(0, 0, d)
            if defl is not None and self.kc == 3:
                v = defl[i].copy(); v[:, 2] = 0
                T = Tpre @ J @ rot4(v) @ Tz
            else:
                T = Tpre @ J @ Tz
            out.append((Tpre, (Tpre @ J)[:, :3, :3], T))
        return out

    def fk(self, x, q):
        """returns dict arm -> (n,3) marker positions in camera frame"""
        sl = self.sl
        n = q.shape[0]
        Tcam = T_C0 @ pert(x[sl["cam"]])
        Pt = [pert(x[sl["pt"]][6 * i:6 * i + 6]) for i in range(4)]
        Pa = {a: [pert(x[sl["p_" + a]][6 * i:6 * i + 6]) for i in range(7)] for a in self.arms}
        qt = np.stack([q[:, 0], q[:, 1], q[:, 2], -q[:, 1] - q[:, 2]], 1)
        qa = {a: q[:, JIDX[a]] for a in self.arms}

        defl_t, defl_a = None, {a: None for a in self.arms}
        if self.kc:
            # ---- pass 1: undeflected geometry for gravity moments ----
            tor = self._chain(F_TORSO, DH["torso"], qt, Pt)
            arm_out = {}
            for a in set(self.arms) | set(self.load_arms):
                Pa_a = Pa[a] if a in Pa else [np.eye(4)] * 7
                arm_out[a] = self._chain(tor[3][2] @ F_BASE[a], DH[a], q[:, JIDX[a]], Pa_a)
            # first moments (sum m p) of arm sub-trees, from distal to proximal
            arm_fm = {}
            for a, ch in arm_out.items():
                mt = np.zeros(7); fm = np.zeros((7, n, 3))
                Ttcp = ch[6][2] @ F_TCP
                acc_m = HAND_M; acc = HAND_M * Ttcp[:, :3, 3]
                for i in range(6, -1, -1):
                    d = DH[a][i, 0]
                    Tl = ch[i][2]
                    com = Tl[:, :3, 3] - 0.5 * d * Tl[:, :3, 2]
                    acc_m = acc_m + ARM_LINK_M; acc = acc + ARM_LINK_M * com
                    mt[i] = acc_m; fm[i] = acc
                arm_fm[a] = (mt, fm)
            def moments(ch, mt, fm):
                res = []
                for i in range(len(ch)):
                    Tpre, Rj, _ = ch[i]
                    o = Tpre[:, :3, 3]
                    Mw = np.cross(fm[i] - mt[i] * o, G)          # (n,3) world moment of gravity
                    Ml = np.einsum("nji,nj->ni", Rj, Mw)           # in joint frame after Rz
                    res.append(Ml)
                return res
            # torso subtree masses
            tm = np.zeros(4); tfm = np.zeros((4, n, 3))
            acc_m = sum(arm_fm[a][0][0] for a in self.load_arms)
            acc = sum(arm_fm[a][1][0] for a in self.load_arms) if self.load_arms else np.zeros((n, 3))
            for i in range(3, -1, -1):
                m, c = TORSO_M[i]
                acc_m = acc_m + m
                acc = acc + m * (tor[i][2][:, :3, :3] @ np.array(c) + tor[i][2][:, :3, 3])
                tm[i] = acc_m; tfm[i] = acc
            Mt = moments(tor, tm, tfm)
            ct = x[sl["ct"]].reshape(4, self.kc)
            defl_t = [self._defl(Mt[i], ct[i]) for i in range(4)]
            for a in self.arms:
                Ma = moments(arm_out[a], *arm_fm[a])
                ca = x[sl["c_" + a]].reshape(7, self.kc)
                defl_a[a] = [self._defl(Ma[i], ca[i]) for i in range(7)]
        # ---- pass 2: (deflected) kinematics ----
        tor = self._chain(F_TORSO, DH["torso"], qt, Pt, defl_t)
        out = {}
        for a in self.arms:
            ch = self._chain(tor[3][2] @ F_BASE[a], DH[a], qa[a], Pa[a], defl_a[a])
            Tm = Tcam @ ch[6][2] @ F_TCP
            m = MARK0[a] + x[sl["m_" + a]] * 1e-3
            out[a] = Tm[:, :3, :3] @ m + Tm[:, :3, 3]
        return out

    def _defl(self, Ml, c):
        """Ml (n,3) moment [Nm] in joint frame; c in mrad per 100 Nm. returns (n,3) rot-vector [rad]
        z = joint compliance, x,y = lateral."""
        v = np.zeros_like(Ml)
        if self.kc == 1:
            v[:, 2] = c[0] * Ml[:, 2] * 1e-5
        else:
            v[:, 2] = c[0] * Ml[:, 2] * 1e-5
            v[:, 0] = c[1] * Ml[:, 0] * 1e-5
            v[:, 1] = c[2] * Ml[:, 1] * 1e-5
        return v

    def resid(self, x, idx):
        p = self.fk(x, Q[idx])
        r = [((p[a] - MEAS[a][idx]) * 1e3).ravel() for a in self.arms]
        r.append(np.sqrt(self.ridge[self.ridge_idx]) * x[self.ridge_idx])
        return np.concatenate(r)

    def fit(self, idx, x0=None, free=None, **kw):
        x0 = np.zeros(self.n) if x0 is None else x0.copy()
        free = np.ones(self.n, bool) if free is None else free
        def f(z):
            x = x0.copy(); x[free] = z
            return self.resid(x, idx)
        r = least_squares(f, x0[free], method="trf", x_scale="jac", diff_step=1e-6, **kw)
        x = x0.copy(); x[free] = r.x
        return x, r

    def errors(self, x, idx):
        p = self.fk(x, Q[idx])
        return {a: np.linalg.norm(p[a] - MEAS[a][idx], axis=1) * 1e3 for a in self.arms}


def stats(e):
    return float(e.mean()), float(np.sqrt((e ** 2).mean()))


def split(s):
    perm = np.random.default_rng(1000 + s).permutation(NP)
    return perm[:350], perm[350:]


def sanity():
    m = Model(("right", "left"))
    free = np.zeros(m.n, bool)
    free[m.sl["cam"]] = True; free[m.sl["m_right"]] = True; free[m.sl["m_left"]] = True
    m.ridge[:] = 0
    x, r = m.fit(np.arange(NP), free=free)
    e = np.concatenate(list(m.errors(x, np.arange(NP)).values()))
    print("sanity cam+markers, all 500 poses, both arms: mean %.2f rms %.2f mm" % stats(e), flush=True)
    return x


def staged_fit(m, tr, x_init):
    """cam+marker first, then geometric, then everything."""
    free = np.zeros(m.n, bool)
    free[m.sl["cam"]] = True
    for a in m.arms:
        free[m.sl["m_" + a]] = True
    x, _ = m.fit(tr, x0=x_init, free=free)
    x, r = m.fit(tr, x0=x, max_nfev=200)
    return x, r


def run_model(name, s, x_san, lam):
    tr, te = split(s)
    res = {}
    t0 = time.time()
    if name in ("A", "B", "B2"):
        for a in ("right", "left"):
            la = ("right", "left") if name == "B2" else (a,)
            m = Model((a,), compl="none" if name == "A" else "joint", load_arms=la, lam=lam)
            x0 = np.zeros(m.n); x0[m.sl["cam"]] = x_san[:6]; x0[m.sl["m_" + a]] = x_san[m_sl_san(a)]
            x, r = staged_fit(m, tr, x0)
            e_tr = m.errors(x, tr)[a]; e = m.errors(x, te)[a]
            res[a] = dict(train=stats(e_tr), test=stats(e), nfev=int(r.nfev), status=int(r.status))
            if m.kc:
                res[a]["ct"] = x[m.sl["ct"]].tolist(); res[a]["ca"] = x[m.sl["c_" + a]].tolist()
    else:
        compl = {"C": "joint", "D": "lateral", "E": "none", "C0": "joint"}[name]
        m = Model(("right", "left"), compl=compl, load_arms=() if name == "C0" else None, lam=lam)
        x0 = np.zeros(m.n); x0[m.sl["cam"]] = x_san[:6]
        for a in ("right", "left"):
            x0[m.sl["m_" + a]] = x_san[m_sl_san(a)]
        x, r = staged_fit(m, tr, x0)
        etr = m.errors(x, tr); ete = m.errors(x, te)
        for a in ("right", "left"):
            res[a] = dict(train=stats(etr[a]), test=stats(ete[a]))
        res["both"] = dict(test=stats(np.concatenate([ete["right"], ete["left"]])))
        res["nfev"], res["status"] = int(r.nfev), int(r.status)
        if m.kc:
            res["ct"] = x[m.sl["ct"]].tolist()
            for a in ("right", "left"):
                res["c_" + a] = x[m.sl["c_" + a]].tolist()
    res["time"] = time.time() - t0
    return res


_SAN = Model(("right", "left"))
def m_sl_san(a):
    return _SAN.sl["m_" + a]


if __name__ == "__main__":
    ap = argparse.ArgumentParser()
    ap.add_argument("--splits", type=int, nargs="+", default=[0, 1, 2])
    ap.add_argument("--models", nargs="+", default=["A", "B", "C", "D"])
    ap.add_argument("--lam", type=float, default=0.01)
    ap.add_argument("--out", default="/tmp/justin_reference.json")
    args = ap.parse_args()
    x_san = sanity()
    allres = {}
    if os.path.exists(args.out):
        allres = json.load(open(args.out))
    for s in args.splits:
        for name in args.models:
            r = run_model(name, s, x_san, args.lam)
            key = f"{name}_s{s}_lam{args.lam}" + (f"_mass{os.environ['JUSTIN_MASS']}" if os.environ.get("JUSTIN_MASS") else "")
            allres[key] = r
            line = f"{key}: " + "  ".join(
                f"{a}: train {r[a]['train'][0]:.2f}/{r[a]['train'][1]:.2f} test {r[a]['test'][0]:.2f}/{r[a]['test'][1]:.2f}"
                for a in ("right", "left"))
            print(line + f"  ({r['time']:.0f}s)", flush=True)
            print("   ", {k: v for k, v in r.items() if k in ("nfev", "status", "ct")},
                  {a: (r[a].get("nfev"), r[a].get("status"), r[a].get("ct")) for a in ("right", "left")}, flush=True)
            json.dump(allres, open(args.out, "w"), indent=1)
