/*
 * tb_registry.c - the tables of model kinds and physics effects, built from tb_registry.def
 * (one line there per kind or effect: nothing to edit here).
 */
#include "tb_internal.h"
#include "tb_physics.h"

/* TB_REGISTRY: another list in the format of tb_registry.def, e.g. the one kind a firmware image
   runs (the linker then leaves the other kinds out); default the full list */
#ifndef TB_REGISTRY
#define TB_REGISTRY "tb_registry.def"
#endif

/* the declarations of every table */
#define TB_KIND(code, name) extern const tbi_kind tbi_kind_##name;
#define TB_EFFECT(code, name) extern const tbi_effect tbi_effect_##name;
#include TB_REGISTRY
#undef TB_KIND
#undef TB_EFFECT

const tbi_kind *const tbi_kinds[TB_KIND_MAX + 1] = {
#define TB_KIND(code, name) [code] = &tbi_kind_##name,
#define TB_EFFECT(code, name)
#include TB_REGISTRY
#undef TB_KIND
#undef TB_EFFECT
};

static const tbi_effect *const effects[TBI_MAX_EFFECT_CODE + 1] = {
#define TB_KIND(code, name)
#define TB_EFFECT(code, name) [code] = &tbi_effect_##name,
#include TB_REGISTRY
#undef TB_KIND
#undef TB_EFFECT
};

const tbi_effect *tbi_effect_of(uint32_t code)
{
    const tbi_effect *e = code <= TBI_MAX_EFFECT_CODE ? effects[code] : 0;
    return e && e->code == code ? e : 0;
}
