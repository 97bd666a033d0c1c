/* Uses the installed package the way the car's controller does: a model, the controller's
 * default configuration, the drive-by-wire endpoint. Exit 0 when all of them initialise. */
#include <stdio.h>
#include <string.h>

#include "ddyn/controller.h"
#include "ddyn/dbw.h"
#include "ddyn_models.h"
#include "ddyn_net_config.h"

static ddyn_ctrl ctl;
static ddyn_dbw dbw;

int consumer_check(void);

int consumer_check(void)
{
    ddyn_ctrl_config cfg;
    ddyn_dbw_config dcfg;
    const ddyn_vehicle_model *model = ddyn_model_find("orca_1_43");
    double x0[DDYN_NX] = {0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.2, 0.0};
    if (model == NULL || ddyn_ctrl_default_config(model, &cfg) != DDYN_OK) {
        return 1;
    }
    /* the car's coefficients come from its configuration; any usable set serves to check the link */
    static const double c[DDYN_NC] = {5.0, 1.2, 0.2, -0.1, 0.0, 0.0, 5.0, 1.2, 0.2, -0.1, 0.0, 0.0, 0.3, 0.05, 0.05,
                                      0.0004, 3e-5};
    memcpy(cfg.c_nominal, c, sizeof c);
    memcpy(cfg.c_fixed, c, sizeof c);
    cfg.coeff_source = DDYN_CTRL_SOURCE_FIXED; /* no network tables needed to check the link */
    if (ddyn_ctrl_init(&ctl, model, NULL, &cfg, x0) != DDYN_OK) {
        return 2;
    }
    ddyn_dbw_default_config(&dcfg, DDYN_DBW_MONITOR_CONTROLLER);
    return ddyn_dbw_init(&dbw, &dcfg) == 0 ? 0 : 3;
}

#ifndef __arm__
int main(void)
{
    int r = consumer_check();
    printf("consumer of the installed ddyn (network %s): %s\n", DDYN_NET_CHECKPOINT_SHA256, r == 0 ? "ok" : "FAILED");
    return r;
}
#endif
