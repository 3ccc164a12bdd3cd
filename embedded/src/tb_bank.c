/*
 * tb_bank.c - a per-condition bank (seed 002 §2.4-2.5): a classifier (tb_kind_classifier.c)
 * picks, at every query, the member model of the condition in force.
 */
#include "tb_internal.h"

int tb_bank_init(tb_bank *b, tb_model *classifier, tb_model *const *members, uint32_t n_members)
{
    uint32_t i;
    if (!b || !classifier || !members || classifier->kind != TB_KIND_CLASSIFIER || !classifier->state) return TB_E_STATE;
    if (n_members != classifier->dims[0] || n_members > TB_MAX_CONDITIONS) return TB_E_ARG;
    for (i = 0; i < n_members; i++)
        if (!members[i] || !members[i]->state || members[i]->kind == TB_KIND_CLASSIFIER) return TB_E_STATE;
    b->classifier = classifier;
    b->n_members = n_members;
    for (i = 0; i < n_members; i++) b->members[i] = members[i];
    return TB_OK;
}

int tb_bank_set_member(tb_bank *b, uint32_t i, tb_model *member)
{
    const tbi_common *c;
    tb_real k_first, k_last, c_first, c_last;
    int k_started;
    if (!b || !b->classifier || i >= b->n_members) return TB_E_ARG;
    if (!member || !member->state || member->kind == TB_KIND_CLASSIFIER) return TB_E_STATE;
    /* a member must have seen the same samples as the bank (its dT baseline is the run's first
     * sample, a physics member integrates from the cold start): swap before the first sample,
     * or bring the new model up to date with the run's log first */
    c = ((const tbi_state *)member->state)->cm;
    if (!c) return TB_E_STATE;
    k_started = tbi_classifier_span(b->classifier, &k_first, &k_last);
    if (k_started != tbi_common_span(c, &c_first, &c_last)) return TB_E_STATE;
    if (k_started && (c_first != k_first || c_last != k_last)) return TB_E_STATE;
    b->members[i] = member;
    return TB_OK;
}

int tb_bank_step(tb_bank *b, const tb_sample *s)
{
    uint32_t i;
    int rc;
    if (!b || !b->classifier) return TB_E_STATE;
    rc = tbi_check_sample(b->classifier, s); /* all or nothing: a sample one model refuses changes none */
    for (i = 0; i < b->n_members && rc == TB_OK; i++) rc = tbi_check_sample(b->members[i], s);
    if (rc != TB_OK) return rc;
    rc = tb_model_step(b->classifier, s);
    if (rc != TB_OK) return rc;
    for (i = 0; i < b->n_members; i++) {
        rc = tb_model_step(b->members[i], s);
        if (rc != TB_OK) return rc;
    }
    return TB_OK;
}

int tb_bank_finish(tb_bank *b)
{
    uint32_t i;
    int rc;
    if (!b || !b->classifier) return TB_E_STATE;
    rc = tb_model_finish(b->classifier);
    for (i = 0; i < b->n_members && rc == TB_OK; i++) rc = tb_model_finish(b->members[i]);
    return rc;
}

tb_real tb_bank_ready_s(const tb_bank *b)
{
    tb_real r;
    uint32_t i;
    if (!b || !b->classifier) return TBI_NO_TIME;
    r = tb_model_ready_s(b->classifier);
    for (i = 0; i < b->n_members; i++) {
        tb_real q = tb_model_ready_s(b->members[i]);
        if (q < r) r = q;
    }
    return r;
}

int tb_bank_predict(const tb_bank *b, tb_real t_s, tb_real axis_mm, tb_real *thermal_um, tb_real *total_um, int32_t *label)
{
    int32_t lab;
    uint32_t i;
    tb_real geo = 0, total = 0;
    int rc;
    if (!b || !b->classifier) return TB_E_STATE;
    rc = tb_classifier_label_at(b->classifier, t_s, &lab);
    if (rc != TB_OK) return rc;
    for (i = 0; i < b->n_members; i++) geo += tb_model_geometric_um(b->members[i], axis_mm);
    geo /= (tb_real)b->n_members;
    if (lab < 0 || (uint32_t)lab >= b->n_members) {
        lab = -1;
        total = geo; /* no condition yet: a cold axis, geometric error only */
    } else {
        rc = tb_model_predict(b->members[lab], t_s, axis_mm, 0, &total);
        if (rc != TB_OK) return rc;
    }
    if (thermal_um) *thermal_um = total - geo;
    if (total_um) *total_um = total;
    if (label) *label = lab;
    return TB_OK;
}
