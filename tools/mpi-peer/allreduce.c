/* The peer the all-reduce benchmark is compared with: MPI_Allreduce (sum of float32) between
 * 2 ranks, timed like worker/benches/allreduce.rs (one warm-up, median of at least `repeats`
 * runs, more for small sizes so at least 64 MB are moved). Prints one key=value line. */
#include <mpi.h>
#include <stdio.h>
#include <stdlib.h>

static int compare(const void *a, const void *b) {
    double x = *(const double *)a, y = *(const double *)b;
    return (x > y) - (x < y);
}

int main(int argc, char **argv) {
    MPI_Init(&argc, &argv);
    int rank;
    MPI_Comm_rank(MPI_COMM_WORLD, &rank);
    int repeats = argc > 1 ? atoi(argv[1]) : 5;
    const double sizes_mb[] = {1, 16, 64, 100};
    if (rank == 0) printf("bench=mpi_allreduce ranks=2 repeats=%d", repeats);
    for (int s = 0; s < 4; s++) {
        size_t count = (size_t)(sizes_mb[s] * 1e6 / 4.0);
        float *send = malloc(count * sizeof(float));
        float *recv = malloc(count * sizeof(float));
        for (size_t i = 0; i < count; i++) send[i] = (float)(i % 1000) + rank;
        int runs = (int)(64.0 / sizes_mb[s] + 0.999);
        if (runs < repeats) runs = repeats;
        if (runs > 500) runs = 500;
        double *times = malloc(runs * sizeof(double));
        for (int run = 0; run <= runs; run++) {
            MPI_Barrier(MPI_COMM_WORLD);
            double start = MPI_Wtime();
            MPI_Allreduce(send, recv, (int)count, MPI_FLOAT, MPI_SUM, MPI_COMM_WORLD);
            double elapsed = MPI_Wtime() - start;
            if (run > 0) times[run - 1] = elapsed;
        }
        qsort(times, runs, sizeof(double), compare);
        double median = times[runs / 2];
        if (rank == 0)
            printf(" time_ms_%gmb=%.3f algbw_gbs_%gmb=%.3f", sizes_mb[s], median * 1e3,
                   sizes_mb[s], sizes_mb[s] / 1e3 / median);
        free(send);
        free(recv);
        free(times);
    }
    if (rank == 0) printf("\n");
    MPI_Finalize();
    return 0;
}
