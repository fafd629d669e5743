/* Scalar C reference of the closed-loop benchmark (benchmarks/throughput/simulate.py).
 *
 * The same discrete algorithm as pmsmjax.simulate for sensored speed control of a
 * three-phase PMSM without flux harmonics (pmsmjax/_sim/_simulate.py, _control/, _plant/_motor.py):
 * sensing -> SensoredObserver -> PI speed control -> id_const current references ->
 * PI current control with decoupling, voltage-circle limit and back-calculation
 * anti-windup -> angle-advanced inverse Park -> ZOH -> classical RK4 of the plant
 * (n_sub substeps per sampling period) -> divergence check -> ISE of the speed error.
 *
 * Scenario: speed reference ramp 0 -> w_final[b] over [0, t_ramp], then constant; load
 * torque steps from 0 to tau_load at t_load; inputs sampled at t_k = k T_s.
 *
 * Compiled by benchmarks/reference/__init__.py: with -DREAL=double and -DREAL=float (then the
 * single-precision libm functions are used). Scalar loop over drives and time; with
 * -fopenmp the loop over drives is split over threads.
 *
 * With -DPMSM_SENSORLESS the loop is sensorless: the angle and speed come from the
 * observer step that `pmsmjax export-c` generated (pmsm_observer.c, found on the include
 * path, in the same precision), fed with the sampled current and the voltage applied over
 * the previous period, as pmsmjax.simulate feeds its observer.
 */
#include <math.h>

#ifndef REAL
#define REAL double
#endif
typedef REAL real;

#ifdef PMSM_SENSORLESS
#include "pmsm_observer.c"
/* the generated step must be in the loop's precision */
typedef char pmsm_real_is_real[(sizeof(pmsm_real) == sizeof(real)) ? 1 : -1];
#endif

#define IS_FLOAT (sizeof(real) == sizeof(float))
#define SIN(x) (IS_FLOAT ? (real)sinf((float)(x)) : (real)sin((double)(x)))
#define COS(x) (IS_FLOAT ? (real)cosf((float)(x)) : (real)cos((double)(x)))
#define SQRT(x) (IS_FLOAT ? (real)sqrtf((float)(x)) : (real)sqrt((double)(x)))
#define FMOD(x, y) (IS_FLOAT ? (real)fmodf((float)(x), (float)(y)) : (real)fmod((double)(x), (double)(y)))

typedef struct {
    /* plant */
    double R_s, L_d, L_q, psi_f, n_p, J, B;
    /* controller model and design */
    double cR_s, cL_d, cL_q, cpsi_f, alpha_c, u_max, J_over_np, alpha_s, tau_max,
           i_d_ref, i_max, k_tau;
    /* sampling, scenario, bounds */
    double T_s, t_ramp, t_load, tau_load, i_bound, w_bound;
    int n_sub;
} params_t;

static const real PI = (real)3.14159265358979323846;

static inline real wrap_angle(real th) {
    /* jnp.remainder (floor modulo) then map -pi to +pi: result in (-pi, pi]. */
    real two_pi = 2 * PI;
    real r = FMOD(th + PI, two_pi);
    if (r != 0 && r < 0) r += two_pi;
    real w = r - PI;
    return (w <= -PI) ? w + two_pi : w;
}

static inline real clip(real x, real lo, real hi) { return x < lo ? lo : (x > hi ? hi : x); }

/* Plant vector field: d/dt (i_d, i_q, theta, w) for u_ab, tau_L held. */
static inline void field(const params_t *p, real id, real iq, real th, real w, real ua,
                         real ub, real tl, real *did, real *diq, real *dth, real *dw) {
    real c = COS(th), s = SIN(th);
    real ud = c * ua + s * ub, uq = -s * ua + c * ub;          /* park(u_ab, theta) */
    real psid = (real)p->L_d * id + (real)p->psi_f, psiq = (real)p->L_q * iq;
    real rd = ud - (real)p->R_s * id + w * psiq;               /* u - R i - w J psi */
    real rq = uq - (real)p->R_s * iq - w * psid;
    *did = rd / (real)p->L_d;
    *diq = rq / (real)p->L_q;
    real tau = (real)(1.5 * p->n_p) * (psid * iq - psiq * id);
    *dw = (real)p->n_p * (tau - (real)p->B * w / (real)p->n_p - tl) / (real)p->J;
    *dth = w;
}

/* One drive: N sampling periods. Writes the final state and the ISE of the speed error. */
static void run_one(const params_t *p, real w_final, int N, real *out) {
    const real T_s = (real)p->T_s;
    real id = 0, iq = 0, th = 0, w = 0;          /* plant */
    real xs = 0, xd = 0, xq = 0;                 /* speed and current integrators */
    real ise = 0;
    int ok = 1;
#ifdef PMSM_SENSORLESS
    pmsm_obs_state obs;
    real u_prev[2] = {0, 0};                     /* applied over the previous period */
    pmsm_obs_init(&obs, 0, 0);                   /* the plant's initial angle and speed */
#endif
    const real kp_s = (real)(2.0 * p->alpha_s * p->J_over_np);
    const real ki_s = (real)(p->alpha_s * p->alpha_s * p->J_over_np);
    const real Kp_d = (real)(p->alpha_c * p->cL_d), Kp_q = (real)(p->alpha_c * p->cL_q);
    const real Ki = (real)(p->alpha_c * p->cR_s);
    const real h = (real)(p->T_s / p->n_sub);
    const real i_d_ref = (real)p->i_d_ref;
    const real iq_den = (real)p->k_tau * ((real)p->cpsi_f + (real)(p->cL_d - p->cL_q) * i_d_ref);
    const real i_q_max = SQRT(fmax((real)p->i_max * (real)p->i_max - i_d_ref * i_d_ref, 0));
    const real u_max = (real)p->u_max, tau_max = (real)p->tau_max;
    for (int k = 0; k < N; ++k) {
        real t = (real)k * T_s;
        real w_ref = t >= (real)p->t_ramp ? w_final : (t / (real)p->t_ramp) * w_final;
        real tl = t >= (real)p->t_load ? (real)p->tau_load : 0;
        /* sensing: current to alpha-beta */
        real c0 = COS(th), s0 = SIN(th);
        real ia = c0 * id - s0 * iq, ib = s0 * id + c0 * iq;
#ifdef PMSM_SENSORLESS
        /* observer: estimated angle and speed from current and previous voltage */
        real i_meas[2] = {ia, ib}, th_hat, w_hat;
        pmsm_obs_step(&obs, i_meas, u_prev, &th_hat, &w_hat);
#else
        /* sensored: the rotor's angle (wrapped) and speed */
        real th_hat = wrap_angle(th), w_hat = w;
#endif
        real ch = COS(th_hat), sh = SIN(th_hat);
        real icd = ch * ia + sh * ib, icq = -sh * ia + ch * ib;
        /* speed PI with anti-windup */
        real e_w = w_ref - w_hat;
        real tau = kp_s * e_w + xs;
        real tau_lim = clip(tau, -tau_max, tau_max);
        xs = xs + T_s * ki_s * (e_w + (tau_lim - tau) / kp_s);
        /* current references (id_const) */
        real i_q_ref = clip(tau_lim / iq_den, -i_q_max, i_q_max);
        /* current PI with decoupling, voltage limit and anti-windup */
        real ed = i_d_ref - icd, eq = i_q_ref - icq;
        real psid = (real)p->cL_d * icd + (real)p->cpsi_f, psiq = (real)p->cL_q * icq;
        real ud = Kp_d * ed + xd - w_hat * psiq;
        real uq = Kp_q * eq + xq + w_hat * psid;
        real n2 = ud * ud + uq * uq;
        real n = SQRT(n2 > 0 ? n2 : 1);
        real sc = n > u_max ? u_max / n : 1;
        real udl = ud * sc, uql = uq * sc;
        xd = xd + T_s * Ki * (ed + (udl - ud) / Kp_d);
        xq = xq + T_s * Ki * (eq + (uql - uq) / Kp_q);
        /* to the stationary frame with angle advance (no inverter delay) */
        real ang = th_hat + (real)0.5 * w_hat * T_s;
        real ca = COS(ang), sa = SIN(ang);
        real ua = ca * udl - sa * uql, ub = sa * udl + ca * uql;
#ifdef PMSM_SENSORLESS
        u_prev[0] = ua;
        u_prev[1] = ub;
#endif
        /* plant: RK4, n_sub steps, increments k = h f */
        ise += T_s * (w_ref - w) * (w_ref - w);
        real y0 = id, y1 = iq, y2 = th, y3 = w;
        for (int j = 0; j < p->n_sub; ++j) {
            real a0, a1, a2, a3, b0, b1, b2, b3, c0_, c1, c2, c3, d0, d1, d2, d3;
            field(p, y0, y1, y2, y3, ua, ub, tl, &a0, &a1, &a2, &a3);
            a0 *= h; a1 *= h; a2 *= h; a3 *= h;
            field(p, y0 + (real)0.5 * a0, y1 + (real)0.5 * a1, y2 + (real)0.5 * a2,
                  y3 + (real)0.5 * a3, ua, ub, tl, &b0, &b1, &b2, &b3);
            b0 *= h; b1 *= h; b2 *= h; b3 *= h;
            field(p, y0 + (real)0.5 * b0, y1 + (real)0.5 * b1, y2 + (real)0.5 * b2,
                  y3 + (real)0.5 * b3, ua, ub, tl, &c0_, &c1, &c2, &c3);
            c0_ *= h; c1 *= h; c2 *= h; c3 *= h;
            field(p, y0 + c0_, y1 + c1, y2 + c2, y3 + c3, ua, ub, tl, &d0, &d1, &d2, &d3);
            d0 *= h; d1 *= h; d2 *= h; d3 *= h;
            const real s6 = (real)(1.0 / 6.0), s3 = (real)(1.0 / 3.0);
            y0 = y0 + (a0 * s6 + b0 * s3 + c0_ * s3 + d0 * s6);
            y1 = y1 + (a1 * s6 + b1 * s3 + c1 * s3 + d1 * s6);
            y2 = y2 + (a2 * s6 + b2 * s3 + c2 * s3 + d2 * s6);
            y3 = y3 + (a3 * s6 + b3 * s3 + c3 * s3 + d3 * s6);
        }
        /* divergence check: freeze the state at the last good sample */
        int good = ok && isfinite(y0) && isfinite(y1) && isfinite(y2) && isfinite(y3) &&
                   (y0 * y0 + y1 * y1 < (real)(p->i_bound * p->i_bound)) &&
                   (fabs(y3) < (real)p->w_bound);
        if (good) { id = y0; iq = y1; th = y2; w = y3; }
        ok = good;
    }
    out[0] = id; out[1] = iq; out[2] = th; out[3] = w; out[4] = ise; out[5] = ok;
}

/* Batch of drives b = 0..B-1 with speed targets w_final[b]; out is (B, 6). */
void simulate_batch(const params_t *p, int B, int N, const real *w_final, real *out) {
#ifdef _OPENMP
#pragma omp parallel for schedule(static)
#endif
    for (int b = 0; b < B; ++b) run_one(p, w_final[b], N, out + 6 * b);
}
