/* fbgforce.h - public API of the fbgforce fixed-point runtime (C99). */
#ifndef FBGFORCE_H
#define FBGFORCE_H

#include <stdint.h>

#define FBG_VERSION_MAJOR 0
#define FBG_VERSION_MINOR 1

/* Library version as (major << 16) | minor, for checking header against library. */
uint32_t fbg_version(void);

#endif /* FBGFORCE_H */
