"""Step control of every time loop, Python and compiled: the tableaux, Hairer's initial
step, the error norms, the accept/reject factors and the continuous extensions, each
defined once. The Python loop (:mod:`natcoord.dynamics.integrators`) and the compiled loops
(:mod:`natcoord.compiled.index1`, :mod:`natcoord.compiled.maggi`) call the same numba functions and
read the same constants, so the loops take the same steps.

Tableaux (module constants, float64): ``RK4_*`` (classical, order 4), ``DOPRI5_*``
(Dormand-Prince 5(4), ``E`` = B - B_embedded, ``P`` (7, 4) the order-4 continuous extension)
and ``DOP853_*`` (Dormand-Prince 8(5,3), Hairer's coefficients: ``A`` (16, 16) holds the 12
stages, the 13th at (t + h, y_new) and the extension's three; ``E5``, ``E3`` (13,) the two
error estimates, ``D`` (4, 16) the extension's last four coefficients).

Step factor after a step with error norm err (<= 1 accepts): h_new = h min(MAX_FACTOR,
SAFETY err^expo) on acceptance (MAX_FACTOR for err = 0), h max(MIN_FACTOR, SAFETY err^expo)
on rejection, expo = -1/8 for dop853, -1/5 for dopri5 (:data:`EXPONENT`).

MAX_FACTOR = 10, by measurement: until this module the compiled index-1 loop let a step grow
by up to 10 and the Python and Maggi loops by up to 5. Every case's natcoord cell
(``natcoord run --engines natcoord``) with 5 in the compiled index-1 loop too: a02_four_bar_n2
takes 1018 steps (301 rejected) instead of 339 (47) and its error against the reference grows
from 2.5e-9 to 1.0e-7 m (over its tolerance), a02_four_bar_n40 1855 steps instead of 1005,
a01_pendulum's error 2.3e-8 instead of 1.6e-8 m; no case gained. (The four-bars pass
singular positions where the step sequence follows round-off: an ulp in the error norm
alone takes a02_four_bar_n2 from 339 to 500 steps, so its figures say more about 5 being
no better than about 10 being best.) With 10 everywhere every compiled index-1 cell is bit
for bit what it was, and the Python and Maggi loops' cells change within their noise
(slider_crank_driven, the one adaptive Python cell: the same 55 steps, 1.3e-13 apart).
10 is scipy's value (Hairer's DOP853 uses 6).
"""

from __future__ import annotations

import numpy as np

try:
    from numba import njit
except ImportError:  # pragma: no cover - numba is a dependency, but stay importable
    def njit(*args, **kwargs):
        if args and callable(args[0]):
            return args[0]
        return lambda f: f

SAFETY = 0.9  # the step factor's safety on the error's estimate of the best step
MIN_FACTOR = 0.2  # a rejected step shrinks by at most 5
MAX_FACTOR = 10.0  # an accepted step grows by at most 10 (measured: see the module's text)
UNDERFLOW = 1e-14  # a step below UNDERFLOW max(1, |t|) s fails the run
STAGE_FAILURE_FACTOR = 0.25  # a stage that failed (Newton in Maggi's positions): h / 4
PROJECTION_FAILURE_FACTOR = 0.5  # a step end index1 cannot project back: h / 2
SAMPLE_TOL = 1e-13  # a sample within SAMPLE_TOL max(1, |t|) of a step end is taken there
EXPONENT = {"dop853": -1.0 / (7 + 1.0), "dopri5": -1.0 / (4 + 1.0)}  # of the step factor

# ---- RK4 -------------------------------------------------------------------------------
RK4_C = np.array([0.0, 0.5, 0.5, 1.0])
RK4_A = np.array([[0, 0, 0, 0], [0.5, 0, 0, 0], [0, 0.5, 0, 0], [0, 0, 1.0, 0]])
RK4_B = np.array([1 / 6, 1 / 3, 1 / 3, 1 / 6])

# ---- DOPRI5 ------------------------------------------------------------------------------
DOPRI5_C = np.array([0, 1 / 5, 3 / 10, 4 / 5, 8 / 9, 1, 1], float)
DOPRI5_A = np.array([
    [0, 0, 0, 0, 0, 0, 0],
    [1 / 5, 0, 0, 0, 0, 0, 0],
    [3 / 40, 9 / 40, 0, 0, 0, 0, 0],
    [44 / 45, -56 / 15, 32 / 9, 0, 0, 0, 0],
    [19372 / 6561, -25360 / 2187, 64448 / 6561, -212 / 729, 0, 0, 0],
    [9017 / 3168, -355 / 33, 46732 / 5247, 49 / 176, -5103 / 18656, 0, 0],
    [35 / 384, 0, 500 / 1113, 125 / 192, -2187 / 6784, 11 / 84, 0]])
DOPRI5_B = np.array([35 / 384, 0, 500 / 1113, 125 / 192, -2187 / 6784, 11 / 84, 0])
DOPRI5_E = DOPRI5_B - np.array([5179 / 57600, 0, 7571 / 16695, 393 / 640, -92097 / 339200,
                                187 / 2100, 1 / 40])
DOPRI5_P = np.array([  # Hairer's order-4 continuous extension (y + h sum_j (K^T P)_j x^j+1)
    [1, -8048581381 / 2820520608, 8663915743 / 2820520608, -12715105075 / 11282082432],
    [0, 0, 0, 0],
    [0, 131558114200 / 32700410799, -68118460800 / 10900136933,
     87487479700 / 32700410799],
    [0, -1754552775 / 470086768, 14199869525 / 1410260304, -10690763975 / 1880347072],
    [0, 127303824393 / 49829197408, -318862633887 / 49829197408,
     701980252875 / 199316789632],
    [0, -282668133 / 205662961, 2019193451 / 616988883, -1453857185 / 822651844],
    [0, 40617522 / 29380423, -110615467 / 29380423, 69997945 / 29380423]])

# ---- DOP853 (Hairer's coefficients as scipy 1.17 writes them, BSD-3-Clause) ----
_C = np.array([0.0,
                0.526001519587677318785587544488e-01,
                0.789002279381515978178381316732e-01,
                0.118350341907227396726757197510,
                0.281649658092772603273242802490,
                0.333333333333333333333333333333,
                0.25,
                0.307692307692307692307692307692,
                0.651282051282051282051282051282,
                0.6,
                0.857142857142857142857142857142,
                1.0,
                1.0,
                0.1,
                0.2,
                0.777777777777777777777777777778])
_A = np.zeros((16, 16))
_A[1, 0] = 5.26001519587677318785587544488e-2
_A[2, 0] = 1.97250569845378994544595329183e-2
_A[2, 1] = 5.91751709536136983633785987549e-2
_A[3, 0] = 2.95875854768068491816892993775e-2
_A[3, 2] = 8.87627564304205475450678981324e-2
_A[4, 0] = 2.41365134159266685502369798665e-1
_A[4, 2] = -8.84549479328286085344864962717e-1
_A[4, 3] = 9.24834003261792003115737966543e-1
_A[5, 0] = 3.7037037037037037037037037037e-2
_A[5, 3] = 1.70828608729473871279604482173e-1
_A[5, 4] = 1.25467687566822425016691814123e-1
_A[6, 0] = 3.7109375e-2
_A[6, 3] = 1.70252211019544039314978060272e-1
_A[6, 4] = 6.02165389804559606850219397283e-2
_A[6, 5] = -1.7578125e-2
_A[7, 0] = 3.70920001185047927108779319836e-2
_A[7, 3] = 1.70383925712239993810214054705e-1
_A[7, 4] = 1.07262030446373284651809199168e-1
_A[7, 5] = -1.53194377486244017527936158236e-2
_A[7, 6] = 8.27378916381402288758473766002e-3
_A[8, 0] = 6.24110958716075717114429577812e-1
_A[8, 3] = -3.36089262944694129406857109825
_A[8, 4] = -8.68219346841726006818189891453e-1
_A[8, 5] = 2.75920996994467083049415600797e1
_A[8, 6] = 2.01540675504778934086186788979e1
_A[8, 7] = -4.34898841810699588477366255144e1
_A[9, 0] = 4.77662536438264365890433908527e-1
_A[9, 3] = -2.48811461997166764192642586468
_A[9, 4] = -5.90290826836842996371446475743e-1
_A[9, 5] = 2.12300514481811942347288949897e1
_A[9, 6] = 1.52792336328824235832596922938e1
_A[9, 7] = -3.32882109689848629194453265587e1
_A[9, 8] = -2.03312017085086261358222928593e-2
_A[10, 0] = -9.3714243008598732571704021658e-1
_A[10, 3] = 5.18637242884406370830023853209
_A[10, 4] = 1.09143734899672957818500254654
_A[10, 5] = -8.14978701074692612513997267357
_A[10, 6] = -1.85200656599969598641566180701e1
_A[10, 7] = 2.27394870993505042818970056734e1
_A[10, 8] = 2.49360555267965238987089396762
_A[10, 9] = -3.0467644718982195003823669022
_A[11, 0] = 2.27331014751653820792359768449
_A[11, 3] = -1.05344954667372501984066689879e1
_A[11, 4] = -2.00087205822486249909675718444
_A[11, 5] = -1.79589318631187989172765950534e1
_A[11, 6] = 2.79488845294199600508499808837e1
_A[11, 7] = -2.85899827713502369474065508674
_A[11, 8] = -8.87285693353062954433549289258
_A[11, 9] = 1.23605671757943030647266201528e1
_A[11, 10] = 6.43392746015763530355970484046e-1
_A[12, 0] = 5.42937341165687622380535766363e-2
_A[12, 5] = 4.45031289275240888144113950566
_A[12, 6] = 1.89151789931450038304281599044
_A[12, 7] = -5.8012039600105847814672114227
_A[12, 8] = 3.1116436695781989440891606237e-1
_A[12, 9] = -1.52160949662516078556178806805e-1
_A[12, 10] = 2.01365400804030348374776537501e-1
_A[12, 11] = 4.47106157277725905176885569043e-2
_A[13, 0] = 5.61675022830479523392909219681e-2
_A[13, 6] = 2.53500210216624811088794765333e-1
_A[13, 7] = -2.46239037470802489917441475441e-1
_A[13, 8] = -1.24191423263816360469010140626e-1
_A[13, 9] = 1.5329179827876569731206322685e-1
_A[13, 10] = 8.20105229563468988491666602057e-3
_A[13, 11] = 7.56789766054569976138603589584e-3
_A[13, 12] = -8.298e-3
_A[14, 0] = 3.18346481635021405060768473261e-2
_A[14, 5] = 2.83009096723667755288322961402e-2
_A[14, 6] = 5.35419883074385676223797384372e-2
_A[14, 7] = -5.49237485713909884646569340306e-2
_A[14, 10] = -1.08347328697249322858509316994e-4
_A[14, 11] = 3.82571090835658412954920192323e-4
_A[14, 12] = -3.40465008687404560802977114492e-4
_A[14, 13] = 1.41312443674632500278074618366e-1
_A[15, 0] = -4.28896301583791923408573538692e-1
_A[15, 5] = -4.69762141536116384314449447206
_A[15, 6] = 7.68342119606259904184240953878
_A[15, 7] = 4.06898981839711007970213554331
_A[15, 8] = 3.56727187455281109270669543021e-1
_A[15, 12] = -1.39902416515901462129418009734e-3
_A[15, 13] = 2.9475147891527723389556272149
_A[15, 14] = -9.15095847217987001081870187138
_E3 = np.zeros(13)
_E3[:-1] = _A[12, :12]
_E3[0] -= 0.244094488188976377952755905512
_E3[8] -= 0.733846688281611857341361741547
_E3[11] -= 0.220588235294117647058823529412e-1
_E5 = np.zeros(13)
_E5[0] = 0.1312004499419488073250102996e-1
_E5[5] = -0.1225156446376204440720569753e+1
_E5[6] = -0.4957589496572501915214079952
_E5[7] = 0.1664377182454986536961530415e+1
_E5[8] = -0.3503288487499736816886487290
_E5[9] = 0.3341791187130174790297318841
_E5[10] = 0.8192320648511571246570742613e-1
_E5[11] = -0.2235530786388629525884427845e-1
# the continuous extension's last four coefficients (the first three come from the step)
_D = np.zeros((4, 16))
_D[0, 0] = -0.84289382761090128651353491142e+1
_D[0, 5] = 0.56671495351937776962531783590
_D[0, 6] = -0.30689499459498916912797304727e+1
_D[0, 7] = 0.23846676565120698287728149680e+1
_D[0, 8] = 0.21170345824450282767155149946e+1
_D[0, 9] = -0.87139158377797299206789907490
_D[0, 10] = 0.22404374302607882758541771650e+1
_D[0, 11] = 0.63157877876946881815570249290
_D[0, 12] = -0.88990336451333310820698117400e-1
_D[0, 13] = 0.18148505520854727256656404962e+2
_D[0, 14] = -0.91946323924783554000451984436e+1
_D[0, 15] = -0.44360363875948939664310572000e+1
_D[1, 0] = 0.10427508642579134603413151009e+2
_D[1, 5] = 0.24228349177525818288430175319e+3
_D[1, 6] = 0.16520045171727028198505394887e+3
_D[1, 7] = -0.37454675472269020279518312152e+3
_D[1, 8] = -0.22113666853125306036270938578e+2
_D[1, 9] = 0.77334326684722638389603898808e+1
_D[1, 10] = -0.30674084731089398182061213626e+2
_D[1, 11] = -0.93321305264302278729567221706e+1
_D[1, 12] = 0.15697238121770843886131091075e+2
_D[1, 13] = -0.31139403219565177677282850411e+2
_D[1, 14] = -0.93529243588444783865713862664e+1
_D[1, 15] = 0.35816841486394083752465898540e+2
_D[2, 0] = 0.19985053242002433820987653617e+2
_D[2, 5] = -0.38703730874935176555105901742e+3
_D[2, 6] = -0.18917813819516756882830838328e+3
_D[2, 7] = 0.52780815920542364900561016686e+3
_D[2, 8] = -0.11573902539959630126141871134e+2
_D[2, 9] = 0.68812326946963000169666922661e+1
_D[2, 10] = -0.10006050966910838403183860980e+1
_D[2, 11] = 0.77771377980534432092869265740
_D[2, 12] = -0.27782057523535084065932004339e+1
_D[2, 13] = -0.60196695231264120758267380846e+2
_D[2, 14] = 0.84320405506677161018159903784e+2
_D[2, 15] = 0.11992291136182789328035130030e+2
_D[3, 0] = -0.25693933462703749003312586129e+2
_D[3, 5] = -0.15418974869023643374053993627e+3
_D[3, 6] = -0.23152937917604549567536039109e+3
_D[3, 7] = 0.35763911791061412378285349910e+3
_D[3, 8] = 0.93405324183624310003907691704e+2
_D[3, 9] = -0.37458323136451633156875139351e+2
_D[3, 10] = 0.10409964950896230045147246184e+3
_D[3, 11] = 0.29840293426660503123344363579e+2
_D[3, 12] = -0.43533456590011143754432175058e+2
_D[3, 13] = 0.96324553959188282948394950600e+2
_D[3, 14] = -0.39177261675615439165231486172e+2
_D[3, 15] = -0.14972683625798562581422125276e+3
DOP853_C, DOP853_A, DOP853_E5, DOP853_E3, DOP853_D = _C, _A, _E5, _E3, _D
DOP853_B = np.append(_A[12, :12], 0.0)  # the 13th stage is f(t + h, y_new): weight 0
del _C, _A, _E5, _E3, _D


# ---- step control ------------------------------------------------------------------------
@njit(cache=True)
def initial_step(d0, d1, span):
    """Hairer's first step (s) from d0 = rms(y / sc) and d1 = rms(f(y) / sc), sc = atol +
    rtol |y|, at most ``span`` (the run's length)."""
    h = 1e-6 if (d0 < 1e-5 or d1 < 1e-5) else 0.01 * d0 / d1
    return min(h, span)


@njit(cache=True)
def dop853_norm(e5, e3, N, h):
    """DOP853's error norm from e5, e3 = sum ((E5 K h) / sc)^2, sum ((E3 K h) / sc)^2 over
    the N components (Hairer's combination of the 5th- and 3rd-order estimates); h = 1, or
    the step when e5 and e3 leave its factor out (one product fewer per component)."""
    if e5 == 0.0 and e3 == 0.0:
        return 0.0
    return h * e5 / np.sqrt((e5 + 0.01 * e3) * N)


@njit(cache=True)
def rms_norm(e, N):
    """The embedded pair's error norm from e = sum ((E K h) / sc)^2 over N components."""
    return np.sqrt(e / N)


@njit(cache=True)
def accept_factor(err, expo):
    """The next step over an accepted one's (err <= 1)."""
    if err == 0.0:
        return MAX_FACTOR
    return min(MAX_FACTOR, SAFETY * err ** expo)


@njit(cache=True)
def reject_factor(err, expo):
    """The retried step over a rejected one's (err > 1)."""
    return max(MIN_FACTOR, SAFETY * err ** expo)


@njit(cache=True)
def underflow(h, t):
    """Whether a step of h (s) at t (s) is too short to go on with."""
    return h < UNDERFLOW * max(1.0, abs(t))


# ---- continuous extensions ---------------------------------------------------------------
@njit(cache=True, inline="always")
def dense_dop853(y, yn, h, K, s_st, D, Fd):
    """The coefficients Fd (3 + d, N) of DOP853's continuous extension (order 7, Hairer's
    CONTD8) on a step of h from y to yn (N,), from its stages K (s_st + 3, N): the step's
    s_st (the last at yn) and the extension's three; D (d, s_st + 3) their weights."""
    for a in range(y.shape[0]):
        dy = yn[a] - y[a]
        Fd[0, a] = dy
        Fd[1, a] = h * K[0, a] - dy
        Fd[2, a] = 2.0 * dy - h * (K[s_st - 1, a] + K[0, a])
    for r in range(D.shape[0]):  # (element loops: a row view costs two reference counts)
        for a in range(y.shape[0]):
            Fd[3 + r, a] = 0.0
        for p in range(D.shape[1]):
            if D[r, p] != 0.0:
                for a in range(y.shape[0]):
                    Fd[3 + r, a] += D[r, p] * K[p, a]
        for a in range(y.shape[0]):
            Fd[3 + r, a] *= h


@njit(cache=True)
def dense_at(Fd, y, x, out):
    """out (N,) = y(t + x h), x in [0, 1], from :func:`dense_dop853`'s Fd: y + the sum of
    Fd[i] times alternating factors x, 1 - x (Horner)."""
    dense_split(Fd, y, x, y.shape[0], out, out)


@njit(cache=True, inline="always")
def dense_split(Fd, y, x, n, q, qd):
    """:func:`dense_at` into two arrays, q (n,) the first n components and qd the rest
    (q may be qd when n = N): per component the same Horner sum, four components of q and
    four of qd at a time held in registers, eight independent chains (rows outer over
    arrays left each row waiting for the last row's stores: twice the time on a small
    model; q's and qd's chains one after the other took a third more than interleaved)."""
    nF, N = Fd.shape[0], y.shape[0]
    x1 = 1.0 - x
    m = N - n
    a = 0
    while a < n or a < m:
        k = max(0, min(4, n - a))  # components a .. a + k - 1 of q, of qd a + n ..
        kd = max(0, min(4, m - a))  # (unused lanes sum zeros)
        s0 = 0.0
        s1 = 0.0
        s2 = 0.0
        s3 = 0.0
        d0 = 0.0
        d1 = 0.0
        d2 = 0.0
        d3 = 0.0
        c = a
        cd = n + a
        for i in range(nF):
            r = nF - 1 - i
            f = x if i % 2 == 0 else x1
            if k > 0:
                s0 = (s0 + Fd[r, c]) * f
            if k > 1:
                s1 = (s1 + Fd[r, c + 1]) * f
            if k > 2:
                s2 = (s2 + Fd[r, c + 2]) * f
            if k > 3:
                s3 = (s3 + Fd[r, c + 3]) * f
            if kd > 0:
                d0 = (d0 + Fd[r, cd]) * f
            if kd > 1:
                d1 = (d1 + Fd[r, cd + 1]) * f
            if kd > 2:
                d2 = (d2 + Fd[r, cd + 2]) * f
            if kd > 3:
                d3 = (d3 + Fd[r, cd + 3]) * f
        if k > 0:
            q[a] = s0 + y[c]
        if k > 1:
            q[a + 1] = s1 + y[c + 1]
        if k > 2:
            q[a + 2] = s2 + y[c + 2]
        if k > 3:
            q[a + 3] = s3 + y[c + 3]
        if kd > 0:
            qd[a] = d0 + y[cd]
        if kd > 1:
            qd[a + 1] = d1 + y[cd + 1]
        if kd > 2:
            qd[a + 2] = d2 + y[cd + 2]
        if kd > 3:
            qd[a + 3] = d3 + y[cd + 3]
        a += 4


@njit(cache=True)
def dense_dopri5(K, P, y, h, x, out):
    """out (N,) = y(t + x h) from DOPRI5's stages K (>= 7, N) and continuous extension P
    (7, 4): y + h sum_j (K^T P)[:, j] x^(j+1) (order 4)."""
    for a in range(y.shape[0]):
        s = 0.0
        for j in range(P.shape[1]):
            qa = 0.0
            for i in range(P.shape[0]):
                qa += K[i, a] * P[i, j]
            s += qa * x ** (j + 1)
        out[a] = y[a] + h * s
