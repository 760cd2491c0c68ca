// Relative-orbit gravity: a MuJoCo engine plugin (passive-force capability).
//
// The MuJoCo world is non-rotating (its axes are those of the inertial frame N) and centred on the chaser,
// which flies a Keplerian orbit. A body at world position rho_N then feels, per unit mass, the differential
// two-body gravity
//     a = -mu (r_c + rho_N) / |r_c + rho_N|^3 + mu r_c / |r_c|^3,
// where r_c(t) is the chaser's inertial position from its orbital elements, evaluated at d->time, so every
// stage of MuJoCo's RK4 sees the gravity of its own instant. Optionally the gravity-gradient torque
//     tau_N = 3 mu / R^5 (R x J_N R),   R = r_c + rho_N,
// is applied too. Units: metres, seconds, kilograms, radians.
//
// Attributes (strings in the MJCF <plugin> element):
//   mu_m3_s2, a_m, e, i_deg, raan_deg, argp_deg, nu0_deg (true anomaly at epoch), epoch_s (sim time of nu0),
//   gravity_gradient (0 or 1).

#ifndef _GNU_SOURCE
#define _GNU_SOURCE  // strtod_l, newlocale: parse numbers in the C locale whatever LC_NUMERIC says
#endif

#include <locale.h>
#include <math.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include <mujoco/mjplugin.h>
#include <mujoco/mujoco.h>

#define PLUGIN_NAME "envisat.relative_gravity"

static const char* kAttributes[] = {"mu_m3_s2", "a_m",     "e",       "i_deg",           "raan_deg",
                                    "argp_deg", "nu0_deg", "epoch_s", "gravity_gradient"};
enum { kNumAttributes = sizeof(kAttributes) / sizeof(kAttributes[0]) };

typedef struct {
  double mu;          // m^3/s^2
  double a, e;        // m, -
  double p_hat[3];    // unit vector to perigee, N
  double q_hat[3];    // unit vector 90 deg ahead of perigee in the orbit plane, N
  double n;           // mean motion, rad/s
  double M0;          // mean anomaly at epoch, rad
  double epoch;       // s
  int gravity_gradient;
} Orbit;

// The "C" numeric locale, made once at library load: MJCF numbers use a decimal point whatever the
// process's LC_NUMERIC (plain strtod would read "0.001" as 0 under a comma-decimal locale).
static locale_t c_numeric_locale = (locale_t)0;

static int is_blank(char c) { return c == ' ' || c == '\t' || c == '\n' || c == '\r' || c == '\f' || c == '\v'; }

// Parses the whole attribute as one finite number (surrounding whitespace allowed, nothing else).
static int read_attribute(const mjModel* m, int instance, const char* name, double* out) {
  const char* text = mj_getPluginConfig(m, instance, name);
  if (!text || !text[0]) {
    mju_warning("%s: attribute '%s' is missing", PLUGIN_NAME, name);
    return -1;
  }
  if (c_numeric_locale == (locale_t)0) {
    mju_warning("%s: could not create the C numeric locale", PLUGIN_NAME);
    return -1;
  }
  char* end = NULL;
  double value = strtod_l(text, &end, c_numeric_locale);
  while (end && is_blank(*end)) ++end;
  if (end == text || !end || *end != '\0' || !isfinite(value)) {
    mju_warning("%s: attribute '%s'='%s' is not a finite number", PLUGIN_NAME, name, text);
    return -1;
  }
  *out = value;
  return 0;
}

// Mean anomaly from true anomaly (elliptic orbit).
static double mean_from_true(double nu, double e) {
  double E = 2.0 * atan2(sqrt(1.0 - e) * sin(0.5 * nu), sqrt(1.0 + e) * cos(0.5 * nu));
  return E - e * sin(E);
}

// Chaser inertial position r_c(t) in N, metres.
static void chief_position(const Orbit* o, double t, double r_c[3]) {
  double M = o->M0 + o->n * (t - o->epoch);
  M = fmod(M, 2.0 * M_PI);
  double E = (o->e < 0.8) ? M : M_PI;
  for (int k = 0; k < 30; ++k) {  // Newton on Kepler's equation E - e sin E = M
    double dE = (E - o->e * sin(E) - M) / (1.0 - o->e * cos(E));
    E -= dE;
    if (fabs(dE) < 1e-15) break;
  }
  double xp = o->a * (cos(E) - o->e);
  double yq = o->a * sqrt(1.0 - o->e * o->e) * sin(E);
  for (int j = 0; j < 3; ++j) r_c[j] = xp * o->p_hat[j] + yq * o->q_hat[j];
}

static int orbit_init(const mjModel* m, int instance, Orbit* o) {
  double v[kNumAttributes];
  for (int k = 0; k < kNumAttributes; ++k) {
    if (read_attribute(m, instance, kAttributes[k], &v[k])) return -1;
  }
  double deg = M_PI / 180.0;
  o->mu = v[0];
  o->a = v[1];
  o->e = v[2];
  if (!(o->mu > 0) || !(o->a > 0) || !(o->e >= 0 && o->e < 1)) {
    mju_warning("%s: need mu > 0, a > 0 and 0 <= e < 1", PLUGIN_NAME);
    return -1;
  }
  double inc = v[3] * deg, raan = v[4] * deg, argp = v[5] * deg, nu0 = v[6] * deg;
  double cO = cos(raan), sO = sin(raan), ci = cos(inc), si = sin(inc), cw = cos(argp), sw = sin(argp);
  o->p_hat[0] = cO * cw - sO * sw * ci;
  o->p_hat[1] = sO * cw + cO * sw * ci;
  o->p_hat[2] = sw * si;
  o->q_hat[0] = -cO * sw - sO * cw * ci;
  o->q_hat[1] = -sO * sw + cO * cw * ci;
  o->q_hat[2] = cw * si;
  o->n = sqrt(o->mu / (o->a * o->a * o->a));
  o->M0 = mean_from_true(nu0, o->e);
  o->epoch = v[7];
  o->gravity_gradient = v[8] != 0.0;
  return 0;
}

static int plugin_nstate(const mjModel* m, int instance) { return 0; }

static int plugin_init(const mjModel* m, mjData* d, int instance) {
  Orbit* o = (Orbit*)calloc(1, sizeof(Orbit));
  if (!o) return -1;
  if (orbit_init(m, instance, o)) {
    free(o);
    return -1;
  }
  d->plugin_data[instance] = (uintptr_t)o;
  return 0;
}

static void plugin_destroy(mjData* d, int instance) {
  free((void*)d->plugin_data[instance]);
  d->plugin_data[instance] = 0;
}

static void plugin_copy(mjData* dest, const mjModel* m, const mjData* src, int instance) {
  Orbit* o = (Orbit*)calloc(1, sizeof(Orbit));
  memcpy(o, (const void*)src->plugin_data[instance], sizeof(Orbit));
  dest->plugin_data[instance] = (uintptr_t)o;
}

static void plugin_reset(const mjModel* m, mjtNum* plugin_state, void* plugin_data, int instance) {}

// Adds the differential gravity (and optional gravity-gradient torque) of every body this instance is
// attached to into qfrc_passive. Uses xipos/ximat, which MuJoCo has updated for the current RK4 stage.
static void plugin_compute(const mjModel* m, mjData* d, int instance, int capability_bit) {
  const Orbit* o = (const Orbit*)d->plugin_data[instance];
  if (!o) return;
  double r_c[3];
  chief_position(o, d->time, r_c);
  double rc2 = r_c[0] * r_c[0] + r_c[1] * r_c[1] + r_c[2] * r_c[2];
  double rc3 = rc2 * sqrt(rc2);
  for (int b = 1; b < m->nbody; ++b) {
    if (m->body_plugin[b] != instance) continue;
    const double* rho = d->xipos + 3 * b;  // CoM in the chaser-centred world, m
    double R[3] = {r_c[0] + rho[0], r_c[1] + rho[1], r_c[2] + rho[2]};
    double R2 = R[0] * R[0] + R[1] * R[1] + R[2] * R[2];
    double R1 = sqrt(R2);
    double R3 = R2 * R1;
    double mass = m->body_mass[b];
    double force[3], torque[3] = {0, 0, 0};
    for (int j = 0; j < 3; ++j) force[j] = mass * o->mu * (-R[j] / R3 + r_c[j] / rc3);
    if (o->gravity_gradient) {
      // J_N R with J_N = ximat diag(body_inertia) ximat^T (principal axes of inertia)
      const double* X = d->ximat + 9 * b;
      const double* Ip = m->body_inertia + 3 * b;
      double Rp[3], JR[3];
      for (int k = 0; k < 3; ++k) Rp[k] = X[0 + k] * R[0] + X[3 + k] * R[1] + X[6 + k] * R[2];
      for (int k = 0; k < 3; ++k) Rp[k] *= Ip[k];
      for (int j = 0; j < 3; ++j) JR[j] = X[3 * j + 0] * Rp[0] + X[3 * j + 1] * Rp[1] + X[3 * j + 2] * Rp[2];
      double s = 3.0 * o->mu / (R3 * R2);
      torque[0] = s * (R[1] * JR[2] - R[2] * JR[1]);
      torque[1] = s * (R[2] * JR[0] - R[0] * JR[2]);
      torque[2] = s * (R[0] * JR[1] - R[1] * JR[0]);
    }
    mj_applyFT(m, d, force, torque, rho, b, d->qfrc_passive);
  }
}

mjPLUGIN_LIB_INIT(envisat_relative_gravity) {
  if (c_numeric_locale == (locale_t)0) c_numeric_locale = newlocale(LC_NUMERIC_MASK, "C", (locale_t)0);
  mjpPlugin plugin;
  mjp_defaultPlugin(&plugin);
  plugin.name = PLUGIN_NAME;
  plugin.capabilityflags |= mjPLUGIN_PASSIVE;
  plugin.nattribute = kNumAttributes;
  plugin.attributes = kAttributes;
  plugin.nstate = plugin_nstate;
  plugin.init = plugin_init;
  plugin.destroy = plugin_destroy;
  plugin.copy = plugin_copy;
  plugin.reset = plugin_reset;
  plugin.compute = plugin_compute;
  mjp_registerPlugin(&plugin);
}
