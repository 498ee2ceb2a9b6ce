/* Prototype (issue 16): sandbox_supervisor.py's steps in C, to see the floor of a task start
 * in a long-lived sandbox without CPython's forks. Not used by osmo; bench_sandbox.py
 * --supervisor compiles it with cc when one is installed.
 *
 * Per line "CWD\tPROGRAM" on stdin: fork; unshare a mount and pid namespace; a private /tmp
 * and /dev/shm; the attempt's folder read-only with work/, output.partial/, files/ writable,
 * staged in the new /dev/shm and moved under the tmpfs that hides HOME; fork pid 1, which
 * mounts /proc and forks the command; the command drops every capability and execs. Writes
 * the exit code.
 *
 * Usage (inside bwrap, as root): sandbox_supervisor HOME ATTEMPT
 */
#define _GNU_SOURCE
#include <sched.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/mount.h>
#include <sys/prctl.h>
#include <sys/stat.h>
#include <sys/syscall.h>
#include <sys/wait.h>
#include <unistd.h>
#include <linux/capability.h>

static void must(int ok, const char *what) {
    if (ok != 0) { perror(what); _exit(255); }
}

static void bind(const char *src, const char *dst, unsigned long rdonly) {
    must(mount(src, dst, NULL, MS_BIND, NULL), src);
    must(mount("none", dst, NULL, MS_REMOUNT | MS_BIND | MS_NOSUID | MS_NODEV | rdonly, NULL),
         dst);
}

static void mkdir_p(const char *path) {
    char buf[4096];
    snprintf(buf, sizeof buf, "%s", path);
    for (char *p = buf + 1; *p; p++)
        if (*p == '/') { *p = 0; mkdir(buf, 0755); *p = '/'; }
    mkdir(buf, 0755);
}

static int code_of(int status) {
    return WIFEXITED(status) ? WEXITSTATUS(status) : 128 + WTERMSIG(status);
}

static int task(const char *home, const char *attempt, const char *cwd, char *prog) {
    static const char *names[] = {"work", "output.partial", "files"};
    char src[4096], dst[4096];
    must(unshare(CLONE_NEWNS | CLONE_NEWPID), "unshare");
    must(mount("none", "/", NULL, MS_REC | MS_PRIVATE, NULL), "private");
    must(mount("tmpfs", "/dev/shm", "tmpfs", MS_NOSUID | MS_NODEV, "mode=1777"), "shm");
    must(mkdir("/dev/shm/.attempt", 0755), "stage");
    bind(attempt, "/dev/shm/.attempt", MS_RDONLY);
    for (int i = 0; i < 3; i++) {
        snprintf(src, sizeof src, "%s/%s", attempt, names[i]);
        snprintf(dst, sizeof dst, "/dev/shm/.attempt/%s", names[i]);
        bind(src, dst, 0);
    }
    must(mount("tmpfs", "/tmp", "tmpfs", MS_NOSUID | MS_NODEV, "mode=1777"), "tmp");
    mkdir_p(home);  /* gone with the host's /tmp when it lies there */
    must(mount("tmpfs", home, "tmpfs", MS_NOSUID | MS_NODEV, "mode=0755"), "home");
    must(mkdir(attempt, 0755), "attempt");  /* attempt is HOME/NAME (one level below) */
    must(mount("/dev/shm/.attempt", attempt, NULL, MS_MOVE, NULL), "move");
    must(rmdir("/dev/shm/.attempt"), "unstage");
    pid_t init = fork();
    if (init == 0) {
        must(mount("proc", "/proc", "proc", MS_NOSUID | MS_NODEV | MS_NOEXEC, NULL), "proc");
        pid_t command = fork();
        if (command == 0) {
            struct __user_cap_header_struct header = {_LINUX_CAPABILITY_VERSION_3, 0};
            struct __user_cap_data_struct data[2] = {{0}};
            for (int cap = 0; cap <= 40; cap++) prctl(PR_CAPBSET_DROP, cap, 0, 0, 0);
            must(prctl(PR_SET_NO_NEW_PRIVS, 1, 0, 0, 0), "nnp");
            must(syscall(SYS_capset, &header, data), "capset");
            must(chdir(cwd), cwd);
            char *argv[] = {prog, NULL};
            execv(prog, argv);
            _exit(127);
        }
        int status;
        pid_t pid;
        while ((pid = wait(&status)) != command)  /* pid 1 reaps orphans */
            if (pid < 0) _exit(255);
        _exit(code_of(status));
    }
    int status;
    waitpid(init, &status, 0);
    return code_of(status);
}

int main(int argc, char **argv) {
    char line[8192];
    if (argc != 3) { fprintf(stderr, "usage: %s HOME ATTEMPT\n", argv[0]); return 2; }
    prctl(PR_SET_PDEATHSIG, 9, 0, 0, 0);
    while (fgets(line, sizeof line, stdin)) {
        line[strcspn(line, "\n")] = 0;
        char *tab = strchr(line, '\t');
        if (!tab) continue;
        *tab = 0;
        pid_t child = fork();
        if (child == 0) _exit(task(argv[1], argv[2], line, tab + 1));
        int status;
        waitpid(child, &status, 0);
        printf("%d\n", code_of(status));
        fflush(stdout);
    }
    return 0;
}
