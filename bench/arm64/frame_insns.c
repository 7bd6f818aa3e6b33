/* QEMU TCG plugin: count the guest instructions executed between markers the guest drops.
 *
 * A marker is the syscall lseek(-1, id, 0x45504f53) (sys=NR: lseek's number, 62 on aarch64) (bench/arm64/frame_insns.py sends one before and
 * after each frame); the plugin appends "id instructions" to out=FILE, the instructions executed since
 * the previous marker by every guest thread together. Counting is inline, per translation block
 * (whole blocks executed), so it costs QEMU little and needs no per-instruction callback.
 *
 * Built against the plugin API header of the QEMU that loads it (scripts/arm64-insns fetches it).
 */
#include <inttypes.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <qemu-plugin.h>

QEMU_PLUGIN_EXPORT int qemu_plugin_version = QEMU_PLUGIN_VERSION;

static int64_t lseek_nr = 62;    /* aarch64's; sys=8 for an x86-64 guest */
#define MARKER_WHENCE 0x45504f53u   /* "EPOS" */

static uint64_t executed;        /* incremented inline by every executed block */
static uint64_t at_last_marker;
static FILE *out;

static void on_translate(qemu_plugin_id_t id, struct qemu_plugin_tb *tb)
{
    qemu_plugin_register_vcpu_tb_exec_inline(tb, QEMU_PLUGIN_INLINE_ADD_U64, &executed,
                                             qemu_plugin_tb_n_insns(tb));
}

static void on_syscall(qemu_plugin_id_t id, unsigned int vcpu, int64_t num, uint64_t a1, uint64_t a2,
                       uint64_t a3, uint64_t a4, uint64_t a5, uint64_t a6, uint64_t a7, uint64_t a8)
{
    if (num != lseek_nr || a1 != UINT64_MAX || (uint32_t)a3 != MARKER_WHENCE)
        return;
    fprintf(out, "%" PRIu64 " %" PRIu64 "\n", a2, executed - at_last_marker);
    fflush(out);
    at_last_marker = executed;
}

static void at_exit(qemu_plugin_id_t id, void *p)
{
    fprintf(out, "total %" PRIu64 "\n", executed);
    fclose(out);
}

QEMU_PLUGIN_EXPORT int qemu_plugin_install(qemu_plugin_id_t id, const qemu_info_t *info, int argc, char **argv)
{
    const char *path = NULL;
    for (int i = 0; i < argc; i++)
        if (strncmp(argv[i], "out=", 4) == 0)
            path = argv[i] + 4;
        else if (strncmp(argv[i], "sys=", 4) == 0)
            lseek_nr = strtoll(argv[i] + 4, NULL, 10);
    if (!path || !(out = fopen(path, "w"))) {
        fprintf(stderr, "frame_insns: give out=FILE (a writable path)\n");
        return -1;
    }
    qemu_plugin_register_vcpu_tb_trans_cb(id, on_translate);
    qemu_plugin_register_vcpu_syscall_cb(id, on_syscall);
    qemu_plugin_register_atexit_cb(id, at_exit, NULL);
    return 0;
}
