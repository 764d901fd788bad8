/* ed25519_driver.c - the vendored verifier (vendor/monocypher) for the tests and the benchmark.
 * Reads lines "PUBLIC_KEY_HEX MESSAGE_HEX SIGNATURE_HEX" (an empty message: "-") and prints
 * crypto_ed25519_check()'s result for each (0 valid, -1 not). With "--bench N" it verifies the
 * first line N times and prints the mean time per verification in microseconds. */
#define _POSIX_C_SOURCE 200809L
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>

#include "monocypher-ed25519.h"

#define MAX_MSG 4096

static size_t unhex(const char *s, uint8_t *out, size_t cap)
{
    size_t n = 0;
    if (strcmp(s, "-") == 0) {
        return 0;
    }
    while (s[0] && s[1] && n < cap) {
        unsigned v;
        if (sscanf(s, "%2x", &v) != 1) {
            break;
        }
        out[n++] = (uint8_t)v;
        s += 2;
    }
    return n;
}

int main(int argc, char **argv)
{
    static char line[3 * 2 * MAX_MSG];
    static uint8_t msg[MAX_MSG];
    long bench = argc == 3 && strcmp(argv[1], "--bench") == 0 ? atol(argv[2]) : 0;
    while (fgets(line, sizeof line, stdin)) {
        char pk_hex[80], sig_hex[160], *msg_hex = malloc(sizeof line);
        uint8_t pk[32] = {0}, sig[64] = {0};
        size_t n;
        if (!msg_hex || sscanf(line, "%79s %s %159s", pk_hex, msg_hex, sig_hex) != 3) {
            free(msg_hex);
            continue;
        }
        unhex(pk_hex, pk, 32);
        unhex(sig_hex, sig, 64);
        n = unhex(msg_hex, msg, MAX_MSG);
        free(msg_hex);
        if (bench > 0) {
            struct timespec a, b;
            long i;
            int ok = 0;
            clock_gettime(CLOCK_MONOTONIC, &a);
            for (i = 0; i < bench; i++) {
                ok |= crypto_ed25519_check(sig, pk, msg, n);
            }
            clock_gettime(CLOCK_MONOTONIC, &b);
            printf("%d %.1f\n", ok,
                   ((double)(b.tv_sec - a.tv_sec) * 1e9 + (double)(b.tv_nsec - a.tv_nsec)) /
                       (double)bench / 1e3);
            return 0;
        }
        printf("%d\n", crypto_ed25519_check(sig, pk, msg, n));
        fflush(stdout);
    }
    return 0;
}
