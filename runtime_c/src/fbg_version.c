#include "fbgforce.h"

uint32_t fbg_version(void)
{
    return ((uint32_t)FBG_VERSION_MAJOR << 16) | (uint32_t)FBG_VERSION_MINOR;
}
