// One persistent CUDA C++ kernel per action-expert decoder layer-step (pi0's Gemma-300M expert).
//
// Compiled at run time by NVRTC (bench/experiments/cuda_layer.py) with the dimensions as macros:
//   W_ width, F_ MLP hidden, NQ query heads (one KV head), D head dim, SEQ tokens, BATCH batch,
//   ROWS = BATCH * SEQ rows (<= 64), KEYS keys in the cache.
// One CTA per SM: 8 consumer warps and 1 producer warp, ~215 KB of shared memory, five grid barriers:
//   1. RMSNorm statistics + QKV GEMM (norm weight folded into its columns, 1 / rms on the output rows),
//      RoPE on interleaved pairs, q to scratch,
//      k / v into the KV cache;
//   2. split-KV attention: (row block of 64 folded query rows) x (48 keys) units, bf16 partials;
//   3. merge of the key slices (element-parallel over the whole grid);
//   4. o projection, split-K over heads; the last CTA of a column tile adds the residual;
//   5. RMSNorm statistics + gate/up GEMM (folded like QKV), GeGLU;
//   6. down projection like 4.
// Weights do not depend on any phase, so the producer warp streams every weight chunk this CTA
// will use in this launch (QKV, o, gate/up, down, in the consumers' order) through a ring of
// shared-memory slots with bulk copies (cp.async.bulk, one per weight row), each slot completing
// on its own mbarrier. It runs ahead across the grid barriers, as far as the ring allows. The
// consumer warps load the activations (cp.async into XOR-swizzled tiles), wait for a slot's
// full barrier, feed both to the tensor cores with ldmatrix + bf16 mma.sync, and free the slot.
// Weight rows sit in a slot with 16 bytes of padding each, so ldmatrix is free of bank conflicts
// without a swizzle that a bulk copy could not apply.
typedef unsigned int u32;
typedef unsigned short u16;

#define THREADS 256                  /* consumer threads; the producer warp is warp 8 */
#define ALL_THREADS (THREADS + 32)
#define NQKV ((NQ + 2) * D)
#define A_ROWS (((ROWS + 7) / 8) * 8)  /* rows of a full-width A tile kept in shared memory */
#define OFF_RING ((A_ROWS * W_ * 2 + 1023) / 1024 * 1024)
#define SLOT 17408                   /* 64 weight rows x (128 + 8) bf16 */
#define NSLOT ((232448 - 1024 - OFF_RING) / SLOT)
#define OFF_STAT (OFF_RING + NSLOT * SLOT)
#define OFF_MBAR (OFF_STAT + 512)
#define SMEM_BYTES (OFF_MBAR + 16 * NSLOT)
#define R_ (SEQ * NQ)                 /* folded query rows per batch element */
#define NRB ((R_ + 63) / 64)
#define KC 48
#define NCH ((KEYS + KC - 1) / KC)
#define GU_KC 128
#define GU_NKC (W_ / GU_KC)
#define QKV_KC 256                   /* QKV chunk: 32 weight rows x 256 */
#define OFF_BIAS 81920              /* attention: 64 x KC bias tile, after Q / K / V */
#define KEYS_PAD (((KEYS + 15) / 16) * 16)

struct Params {
  const u16* x; const u16* wqkv; const u16* g1; const float* cos; const float* sin;
  u16* q; u16* k_out; u16* v_out; const u16* k_all; const u16* v_all; const u16* bias;
  float* apart; float* aml; u16* attn;
  const u16* wo; float* part; u16* x1; const u16* g2; const u16* wgu; u16* h; const u16* wd; u16* out;
  int* cnt; u32* bar; long long* stamps;
  const float* ss_in;  // sums of squares of x per (64-column tile, row) from the previous launch, or null
  float* ss_mid; float* ss_out;  // the same for x1 (o phase -> gate/up) and out (down -> next launch)
  const u16* wqkv_next;  // the next layer's (folded) QKV weight, prefetched into L2, or null
  long long cos_sb, cos_ss, k_sb, k_ss, v_sb, v_ss, ka_sb, ka_ss, va_sb, va_ss, b_sb, b_sm;
  float eps, scale;
};

__device__ __forceinline__ u32 smem_addr(const void* p) {
  u32 r;
  asm("{ .reg .u64 t; cvta.to.shared.u64 t, %1; cvt.u32.u64 %0, t; }" : "=r"(r) : "l"(p));
  return r;
}
__device__ __forceinline__ void cp16(u32 dst, const void* src, bool valid) {
  asm volatile("cp.async.cg.shared.global [%0], [%1], 16, %2;" :: "r"(dst), "l"(src), "r"(valid ? 16 : 0));
}
__device__ __forceinline__ void cp_commit() { asm volatile("cp.async.commit_group;"); }
template <int N> __device__ __forceinline__ void cp_wait() { asm volatile("cp.async.wait_group %0;" :: "n"(N)); }

// The consumer warps' own CTA barrier (named barrier 1): the producer warp never joins it.
__device__ __forceinline__ void csync() { asm volatile("bar.sync 1, %0;" :: "n"(THREADS) : "memory"); }

__device__ __forceinline__ void mbar_init(u32 bar, u32 count) {
  asm volatile("mbarrier.init.shared::cta.b64 [%0], %1;" :: "r"(bar), "r"(count) : "memory");
}
__device__ __forceinline__ void mbar_wait(u32 bar, u32 parity) {
  u32 done;
  do {
    asm volatile("{ .reg .pred p; mbarrier.try_wait.parity.shared::cta.b64 p, [%1], %2; selp.u32 %0, 1, 0, p; }"
                 : "=r"(done) : "r"(bar), "r"(parity) : "memory");
  } while (!done);
}
__device__ __forceinline__ void mbar_arrive(u32 bar) {
  asm volatile("mbarrier.arrive.shared::cta.b64 _, [%0];" :: "r"(bar) : "memory");
}
__device__ __forceinline__ void mbar_expect_tx(u32 bar, u32 bytes) {
  asm volatile("mbarrier.arrive.expect_tx.shared::cta.b64 _, [%0], %1;" :: "r"(bar), "r"(bytes) : "memory");
}
// Bulk copy global -> shared (the TMA engine, no registers): completes `bytes` on mbarrier `bar`.
__device__ __forceinline__ void bulk_g2s(u32 dst, const void* src, u32 bytes, u32 bar) {
  asm volatile("cp.async.bulk.shared::cluster.global.mbarrier::complete_tx::bytes [%0], [%1], %2, [%3];"
               :: "r"(dst), "l"(src), "r"(bytes), "r"(bar) : "memory");
}

// The weight ring. Producer and consumers walk the same sequence of chunks, so one counter
// `it` each gives the slot (it % NSLOT) and the phase parity of its barriers (it / NSLOT).
struct Ring {
  u32 base, full, empty, it;
  __device__ __forceinline__ u32 slot() const { return base + (it % NSLOT) * SLOT; }
  __device__ __forceinline__ void wait_full() const { mbar_wait(full + (it % NSLOT) * 8, (it / NSLOT) & 1); }
  // Each consumer warp frees the slot once all its lanes are done reading it.
  __device__ __forceinline__ void release() {
    __syncwarp();
    if ((threadIdx.x & 31) == 0) mbar_arrive(empty + (it % NSLOT) * 8);
    ++it;
  }
};

__device__ __forceinline__ void ldsm4(u32* r, u32 addr) {
  asm volatile("ldmatrix.sync.aligned.m8n8.x4.shared.b16 {%0,%1,%2,%3}, [%4];"
               : "=r"(r[0]), "=r"(r[1]), "=r"(r[2]), "=r"(r[3]) : "r"(addr));
}
__device__ __forceinline__ void ldsm4t(u32* r, u32 addr) {
  asm volatile("ldmatrix.sync.aligned.m8n8.x4.trans.shared.b16 {%0,%1,%2,%3}, [%4];"
               : "=r"(r[0]), "=r"(r[1]), "=r"(r[2]), "=r"(r[3]) : "r"(addr));
}
__device__ __forceinline__ void mma(float* c, const u32* a, u32 b0, u32 b1) {
  asm volatile("mma.sync.aligned.m16n8k16.row.col.f32.bf16.bf16.f32 {%0,%1,%2,%3}, {%4,%5,%6,%7}, {%8,%9}, {%0,%1,%2,%3};"
               : "+f"(c[0]), "+f"(c[1]), "+f"(c[2]), "+f"(c[3])
               : "r"(a[0]), "r"(a[1]), "r"(a[2]), "r"(a[3]), "r"(b0), "r"(b1));
}
__device__ __forceinline__ u32 pack_bf16(float lo, float hi) {
  u32 r;
  asm("cvt.rn.bf16x2.f32 %0, %1, %2;" : "=r"(r) : "f"(hi), "f"(lo));
  return r;
}
__device__ __forceinline__ float bf16f(u16 v) { return __uint_as_float(((u32)v) << 16); }
__device__ __forceinline__ float round_bf16(float v) { return __uint_as_float(pack_bf16(v, 0.f) << 16); }
__device__ __forceinline__ u16 to_bf16(float v) { return (u16)(pack_bf16(v, 0.f) & 0xffff); }
__device__ __forceinline__ float ldcg(const float* p) {
  float v;
  asm volatile("ld.global.cg.f32 %0, [%1];" : "=f"(v) : "l"(p));
  return v;
}
__device__ __forceinline__ u16 ldcg_u16(const u16* p) {
  u16 v;
  asm volatile("ld.global.cg.u16 %0, [%1];" : "=h"(v) : "l"(p));
  return v;
}

// Byte offset of 16-byte chunk `chunk` of row `row` in a tile of `rowbytes` per row. XOR-ing the
// chunk with the row's low 3 bits spreads the 8 rows that one ldmatrix reads over all banks.
__device__ __forceinline__ u32 swz(int row, int chunk, int rowbytes) {
  return row * rowbytes + ((chunk ^ (row & 7)) << 4);
}

// cp.async a rows x cols (bf16) tile into shared memory; rows >= valid are zero-filled.
template <class RowPtr>
__device__ __forceinline__ void load_tile(u32 sbase, int rows, int cols, int valid, RowPtr rp) {
  const int cpr = cols / 8, total = rows * cpr;
  for (int i = threadIdx.x; i < total; i += THREADS) {
    const int r = i / cpr, c = i - r * cpr;
    const bool ok = r < valid;
    cp16(sbase + swz(r, c, cols * 2), ok ? (const void*)(rp(r) + c * 8) : (const void*)rp(0), ok);
  }
}

// acc[MT][NT] += A[a_row0 + 16 MT rows, k16 at a_chunk] * B[b_row0 + 8 NT rows, k16 at b_chunk]^T
template <int MT, int NT, bool BPAD = false>
__device__ __forceinline__ void mma_k16(float (*acc)[NT][4], u32 a_base, int a_row0, int a_rowbytes, int a_chunk,
                                        u32 b_base, int b_row0, int b_rowbytes, int b_chunk, int lane) {
  u32 a[MT][4];
#pragma unroll
  for (int mt = 0; mt < MT; ++mt) {
    const int row = a_row0 + mt * 16 + (lane & 7) + 8 * ((lane >> 3) & 1);
    ldsm4(a[mt], a_base + swz(row, a_chunk + (lane >> 4), a_rowbytes));
  }
#pragma unroll
  for (int n2 = 0; n2 < NT / 2; ++n2) {
    u32 b[4];
    const int row = b_row0 + n2 * 16 + (lane & 7) + 8 * (lane >> 4);
    const int bc = b_chunk + ((lane >> 3) & 1);
    ldsm4(b, b_base + (BPAD ? row * (b_rowbytes + 16) + (bc << 4) : swz(row, bc, b_rowbytes)));
#pragma unroll
    for (int mt = 0; mt < MT; ++mt) {
      mma(acc[mt][2 * n2], a[mt], b[0], b[1]);
      mma(acc[mt][2 * n2 + 1], a[mt], b[2], b[3]);
    }
  }
}

// Store a warp's 64 x (8 NT) accumulator tile at column col0 of an fp32 tile with rs floats per row.
template <int NT>
__device__ __forceinline__ void store_acc(float (*acc)[NT][4], float* red, int rs, int col0, int lane) {
#pragma unroll
  for (int mt = 0; mt < 4; ++mt)
#pragma unroll
    for (int nt = 0; nt < NT; ++nt) {
      const int r = mt * 16 + (lane >> 2), c = col0 + nt * 8 + 2 * (lane & 3);
      *(float2*)(red + r * rs + c) = make_float2(acc[mt][nt][0], acc[mt][nt][1]);
      *(float2*)(red + (r + 8) * rs + c) = make_float2(acc[mt][nt][2], acc[mt][nt][3]);
    }
}

template <int MT, int NT>
__device__ __forceinline__ void zero(float (*acc)[NT][4]) {
#pragma unroll
  for (int mt = 0; mt < MT; ++mt)
#pragma unroll
    for (int nt = 0; nt < NT; ++nt)
#pragma unroll
      for (int e = 0; e < 4; ++e) acc[mt][nt][e] = 0.f;
}

// 1 / rms of each of the ROWS rows of a W_-wide bf16 tile, into stat. The norm weight is folded
// into the next GEMM's weight columns on the host, and 1 / rms scales that GEMM's output rows,
// so the tile itself goes to the tensor cores untouched.
__device__ void rms_stat(const unsigned char* tile, float eps, float* stat) {
  const int lane = threadIdx.x & 31, warp = threadIdx.x >> 5;
  for (int r = warp; r < ROWS; r += THREADS / 32) {
    float ss = 0.f;
    for (int c = lane; c < W_ / 8; c += 32) {  // the swizzle permutes chunks within a row: no matter here
      const uint4 v = *(const uint4*)(tile + r * W_ * 2 + c * 16);
      const u32 w4[4] = {v.x, v.y, v.z, v.w};
#pragma unroll
      for (int e = 0; e < 4; ++e) {
        const float lo = __uint_as_float(w4[e] << 16), hi = __uint_as_float(w4[e] & 0xffff0000u);
        ss += lo * lo + hi * hi;
      }
    }
#pragma unroll
    for (int o = 16; o; o >>= 1) ss += __shfl_xor_sync(0xffffffffu, ss, o);
    if (lane == 0) stat[r] = rsqrtf(ss / W_ + eps);
  }
}

__device__ __forceinline__ void grid_sync(u32* bar, u32 target) {
  csync();
  if (threadIdx.x == 0) {
    __threadfence();
    asm volatile("red.release.gpu.global.add.u32 [%0], 1;" :: "l"(bar) : "memory");
    u32 v;
    do {
      asm volatile("ld.acquire.gpu.global.u32 %0, [%1];" : "=r"(v) : "l"(bar) : "memory");
    } while (v < target);
    __threadfence();
  }
  csync();
}

__device__ __forceinline__ void stamp(const Params& p, int idx) {
  if (p.stamps != nullptr && threadIdx.x == 0) {
    unsigned long long t;
    asm volatile("mov.u64 %0, %%globaltimer;" : "=l"(t));
    p.stamps[blockIdx.x * 16 + idx] = (long long)t;
  }
}

// Split-K epilogue: this CTA's partial of column tile nt (64 columns) goes to global memory; the
// last of the SPLITS CTAs of the tile sums all partials in a fixed order, adds the residual
// and writes bf16. The SPLITS loads of an element are issued together (one L2 round trip).
template <int SPLITS>
__device__ void splitk_finish(const Params& p, unsigned char* smem, const float* red, int nt, int ks, int cnt_idx,
                              const u16* residual, u16* out, float* ss_out, int* last_flag) {
  float* mine = p.part + (long long)(ks * (W_ / 64) + nt) * 64 * 64;
  for (int i = threadIdx.x; i < ROWS * 16; i += THREADS) {
    const int r = i >> 4, c = (i & 15) * 4;
    const float* a = red + r * 68 + c;
    const float* b = red + 64 * 68 + r * 68 + c;
    *(float4*)(mine + r * 64 + c) = make_float4(a[0] + b[0], a[1] + b[1], a[2] + b[2], a[3] + b[3]);
  }
  // One release by thread 0 after the CTA barrier publishes every thread's partial (PTX release
  // is cumulative), instead of a fence per thread; its acquire orders the last CTA's reads.
  csync();
  if (threadIdx.x == 0) {
    int old;
    asm volatile("atom.acq_rel.gpu.global.add.s32 %0, [%1], 1;" : "=r"(old) : "l"(p.cnt + cnt_idx) : "memory");
    *last_flag = old == SPLITS - 1;
  }
  csync();
  if (*last_flag) {
    // All partials and the residual tile come into shared memory in one asynchronous round trip
    // (over this unit's A and reduction tiles, which are done), instead of one L2 round trip per
    // pass of the loop below.
    const u32 s0 = smem_addr(smem);
    constexpr int PART_BYTES = SPLITS * ROWS * 256;
    static_assert(PART_BYTES + ROWS * 128 <= OFF_RING, "split-K staging must fit the activation region");
    for (int i = threadIdx.x; i < SPLITS * ROWS * 16; i += THREADS) {
      const int sp = i / (ROWS * 16), rem = i - sp * ROWS * 16, r = rem >> 4, c = rem & 15;
      cp16(s0 + i * 16, p.part + (long long)(sp * (W_ / 64) + nt) * 64 * 64 + r * 64 + c * 4, true);
    }
    for (int i = threadIdx.x; i < ROWS * 8; i += THREADS)
      cp16(s0 + PART_BYTES + i * 16, residual + (i >> 3) * W_ + nt * 64 + (i & 7) * 8, true);
    cp_commit();
    cp_wait<0>();
    csync();
    const float* sp_ = (const float*)smem;
    const u16* sres = (const u16*)(smem + PART_BYTES);
    // Every row's 16 threads sit in one warp, so each pass covers whole rows and the sum of
    // squares of the tile's 64 written values reduces over 16 lanes.
    for (int i0 = 0; i0 < ROWS * 16; i0 += THREADS) {
      const int i = i0 + threadIdx.x, r = i >> 4, c = (i & 15) * 4;
      float ss = 0.f;
      if (i < ROWS * 16) {
        float s0f = 0.f, s1f = 0.f, s2f = 0.f, s3f = 0.f;
#pragma unroll
        for (int sp = 0; sp < SPLITS; ++sp) {
          const float4 v = *(const float4*)(sp_ + (sp * ROWS + r) * 64 + c);
          s0f += v.x; s1f += v.y; s2f += v.z; s3f += v.w;
        }
        const uint2 res = *(const uint2*)(sres + r * 64 + c);
        const float o0 = __uint_as_float(res.x << 16), o1 = __uint_as_float(res.x & 0xffff0000u);
        const float o2 = __uint_as_float(res.y << 16), o3 = __uint_as_float(res.y & 0xffff0000u);
        const uint2 o = make_uint2(pack_bf16(s0f + o0, s1f + o1), pack_bf16(s2f + o2, s3f + o3));
        *(uint2*)(out + r * W_ + nt * 64 + c) = o;
        const float e0 = __uint_as_float(o.x << 16), e1 = __uint_as_float(o.x & 0xffff0000u);
        const float e2 = __uint_as_float(o.y << 16), e3 = __uint_as_float(o.y & 0xffff0000u);
        ss = e0 * e0 + e1 * e1 + e2 * e2 + e3 * e3;
      }
#pragma unroll
      for (int o = 8; o; o >>= 1) ss += __shfl_xor_sync(0xffffffffu, ss, o);
      if (i < ROWS * 16 && (i & 15) == 0) ss_out[nt * 64 + r] = ss;
    }
    if (threadIdx.x == 0) p.cnt[cnt_idx] = 0;
  }
  csync();
}

// 1 / rms per row from the per-column-tile sums of squares that the phase writing the tile left.
__device__ __forceinline__ void rms_from_partials(const float* ss, float eps, float* stat) {
  for (int r = threadIdx.x; r < ROWS; r += THREADS) {
    float t = 0.f;
#pragma unroll
    for (int nt = 0; nt < W_ / 64; ++nt) t += ldcg(ss + nt * 64 + r);
    stat[r] = rsqrtf(t / W_ + eps);
  }
}

// One unit of a split-K projection that adds the residual (o: KU = 256 of the 2048 attention
// columns; down: KU = 512 of the 4096 MLP columns). Its weights arrive through the ring in
// chunks of 64 rows x 128.
template <int KU, int SPLITS>
__device__ __forceinline__ void residual_unit(const Params& p, unsigned char* smem, Ring& ring, int u, u32 red_off,
                                              const u16* a, int lda, int cnt_base, const u16* residual, u16* out,
                                              float* ss_out, int* last_flag, int stamp_idx) {
  const u32 sb = smem_addr(smem);
  const int lane = threadIdx.x & 31, warp = threadIdx.x >> 5;
  const int nt = u % (W_ / 64), ks = u / (W_ / 64);
  load_tile(sb, 64, KU, ROWS, [&](int r) { return a + (long long)r * lda + ks * KU; });
  cp_commit();
  cp_wait<0>();
  csync();
  if (u == (int)blockIdx.x) stamp(p, stamp_idx);
  const int kg = warp >> 2, ng = warp & 3;  // 2 K halves of each chunk x 4 column groups of 16
  float acc[4][2][4];
  zero<4, 2>(acc);
  for (int c = 0; c < KU / 128; ++c) {
    ring.wait_full();
    const u32 w = ring.slot();
#pragma unroll
    for (int kk = 0; kk < 4; ++kk) {
      const int k16 = kg * 4 + kk;
      mma_k16<4, 2, true>(acc, sb, 0, KU * 2, (c * 128 + k16 * 16) / 8, w, ng * 16, 256, k16 * 2, lane);
    }
    ring.release();
  }
  float* red = (float*)(smem + red_off);
  store_acc<2>(acc, red + kg * 64 * 68, 68, ng * 16, lane);
  csync();
  splitk_finish<SPLITS>(p, smem, red, nt, ks, cnt_base + nt, residual, out, ss_out, last_flag);
}

// The producer warp: every weight chunk of this CTA's units, in the order the consumers use them.
__device__ void produce_weights(const Params& p, Ring ring) {
  const int lane = threadIdx.x & 31, G = gridDim.x;
  auto put = [&](int rows, int rowbytes, auto src) {
    const int s = ring.it % NSLOT;
    mbar_wait(ring.empty + s * 8, ((ring.it / NSLOT) & 1) ^ 1);
    if (lane == 0) mbar_expect_tx(ring.full + s * 8, rows * rowbytes);
    __syncwarp();
    const u32 dst = ring.base + s * SLOT;
    for (int r = lane; r < rows; r += 32) bulk_g2s(dst + r * (rowbytes + 16), src(r), rowbytes, ring.full + s * 8);
    ++ring.it;
  };
  for (int u = blockIdx.x; u < NQKV / 32; u += G)
    for (int c = 0; c < W_ / QKV_KC; ++c)
      put(32, QKV_KC * 2, [&](int r) { return p.wqkv + (long long)(u * 32 + r) * W_ + c * QKV_KC; });
  for (int u = blockIdx.x; u < (W_ / 64) * (NQ * D / 256); u += G) {
    const int nt = u % (W_ / 64), ks = u / (W_ / 64);
    for (int c = 0; c < 2; ++c)
      put(64, 256, [&](int r) { return p.wo + (long long)(nt * 64 + r) * NQ * D + ks * 256 + c * 128; });
  }
  for (int u = blockIdx.x; u < F_ / 32; u += G)
    for (int c = 0; c < GU_NKC; ++c)
      put(64, GU_KC * 2, [&](int r) {
        const long long row = r < 32 ? u * 32 + r : F_ + u * 32 + r - 32;
        return p.wgu + row * W_ + c * GU_KC;
      });
  for (int u = blockIdx.x; u < (W_ / 64) * (F_ / 512); u += G) {
    const int nt = u % (W_ / 64), ks = u / (W_ / 64);
    for (int c = 0; c < 4; ++c)
      put(64, 256, [&](int r) { return p.wd + (long long)(nt * 64 + r) * F_ + ks * 512 + c * 128; });
  }
  // The next launch's first phase would wait on HBM for its QKV weights while every CTA also
  // fills its ring; bring this CTA's share of them into L2 now (32 rows of W: 64 KB, contiguous).
  if (p.wqkv_next != nullptr && lane == 0)
    for (int u = blockIdx.x; u < NQKV / 32; u += G)
      asm volatile("cp.async.bulk.prefetch.L2.global [%0], %1;" :: "l"(p.wqkv_next + (long long)u * 32 * W_),
                   "r"(32 * W_ * 2) : "memory");
}

extern "C" __global__ void __launch_bounds__(ALL_THREADS, 1) layer_step(const Params p) {
  extern __shared__ __align__(1024) unsigned char smem[];
  static_assert(OFF_RING >= 100352, "the activation region must hold every phase's tiles");
  static_assert(NSLOT >= 2 && ROWS <= 64, "ring and row limits");
  const u32 sb = smem_addr(smem);
  const int tid = threadIdx.x, lane = tid & 31, warp = tid >> 5;
  const int G = gridDim.x;
  float* stat = (float*)(smem + OFF_STAT);
  __shared__ int last_flag;
  Ring ring{sb + OFF_RING, sb + OFF_MBAR, sb + OFF_MBAR + 8 * NSLOT, 0};
  if (tid == 0) {
    for (int s = 0; s < NSLOT; ++s) {
      mbar_init(ring.full + s * 8, 1);
      mbar_init(ring.empty + s * 8, THREADS / 32);
    }
    asm volatile("fence.mbarrier_init.release.cluster;" ::: "memory");
    asm volatile("fence.proxy.async.shared::cta;" ::: "memory");
  }
  __syncthreads();
  if (warp == THREADS / 32) {
    produce_weights(p, ring);
    return;
  }
  u32 epoch = 0;
  stamp(p, 0);

  // ---------------------------------------------------------------- 1. norm + QKV + RoPE
  for (int u = blockIdx.x; u < NQKV / 32; u += G) {
    load_tile(sb, A_ROWS, W_, ROWS, [&](int r) { return p.x + (long long)r * W_; });
    cp_commit();
    if (p.ss_in != nullptr) rms_from_partials(p.ss_in, p.eps, stat);  // while the tile lands; read after a csync
    cp_wait<0>();
    csync();
    if (u == (int)blockIdx.x) stamp(p, 1);
    if (p.ss_in == nullptr) rms_stat(smem, p.eps, stat);
    // This thread's RoPE factors for the epilogue, requested now so their L2 round trip
    // overlaps the mma instead of following it.
    constexpr int EPI = (ROWS * 16 + THREADS - 1) / THREADS;
    float rc[EPI], rs[EPI];
#pragma unroll
    for (int e = 0; e < EPI; ++e) {
      const int i = tid + e * THREADS, r = i >> 4, n = u * 32 + (i & 15) * 2, bb = r / SEQ, s = r - bb * SEQ;
      rc[e] = rs[e] = 0.f;
      if (i < ROWS * 16 && n < NQ * D + D) {
        const int j = (n % D) >> 1;
        rc[e] = p.cos[bb * p.cos_sb + s * p.cos_ss + j];
        rs[e] = p.sin[bb * p.cos_sb + s * p.cos_ss + j];
      }
    }
    float acc[4][4][4];
    zero<4, 4>(acc);
    for (int c = 0; c < W_ / QKV_KC; ++c) {  // warp w: k16 steps 2w, 2w + 1 of each chunk
      ring.wait_full();
      const u32 w = ring.slot();
#pragma unroll
      for (int kk = 0; kk < 2; ++kk) {
        const int k16 = warp * 2 + kk;
        mma_k16<4, 4, true>(acc, sb, 0, W_ * 2, (c * QKV_KC + k16 * 16) / 8, w, 0, QKV_KC * 2, k16 * 2, lane);
      }
      ring.release();
    }
    csync();
    float* red = (float*)smem;  // 8 warps x 64 x 36 floats = 73.7 KB, over the A tile (done)
    store_acc<4>(acc, red + warp * 64 * 36, 36, 0, lane);
    csync();
#pragma unroll
    for (int e = 0; e < EPI; ++e) {
      const int i = tid + e * THREADS, r = i >> 4, c = (i & 15) * 2;
      if (i >= ROWS * 16) break;
      float a0 = 0.f, a1 = 0.f;
#pragma unroll
      for (int w = 0; w < 8; ++w) {
        a0 += red[w * 64 * 36 + r * 36 + c];
        a1 += red[w * 64 * 36 + r * 36 + c + 1];
      }
      a0 = round_bf16(a0 * stat[r]);
      a1 = round_bf16(a1 * stat[r]);
      const int n = u * 32 + c, bb = r / SEQ, s = r - bb * SEQ;
      if (n < NQ * D + D) {
        const int dd = n % D;
        const float cs = rc[e], sn = rs[e];
        const u32 v = pack_bf16(a0 * cs - a1 * sn, a0 * sn + a1 * cs);
        if (n < NQ * D) *(u32*)(p.q + (long long)r * NQ * D + n) = v;
        else *(u32*)(p.k_out + bb * p.k_sb + s * p.k_ss + dd) = v;
      } else {
        *(u32*)(p.v_out + bb * p.v_sb + s * p.v_ss + (n - NQ * D - D)) = pack_bf16(a0, a1);
      }
    }
    csync();
  }
  stamp(p, 2);
  grid_sync(p.bar, ++epoch * G);

  // ---------------------------------------------------------------- 2. split-KV attention
  for (int u = blockIdx.x; u < BATCH * NRB * NCH; u += G) {
    const int ch = u % NCH, rb = (u / NCH) % NRB, bb = u / (NCH * NRB);
    const int r0 = rb * 64, k0 = ch * KC;
    const u32 sq = sb, sk = sb + 32768, sv = sb + 32768 + KC * D * 2;
    load_tile(sq, 64, D, min(64, R_ - r0), [&](int r) { return p.q + ((long long)bb * R_ + r0 + r) * D; });
    load_tile(sk, KC, D, min(KC, KEYS - k0), [&](int r) { return p.k_all + bb * p.ka_sb + (long long)(k0 + r) * p.ka_ss; });
    load_tile(sv, KC, D, min(KC, KEYS - k0), [&](int r) { return p.v_all + bb * p.va_sb + (long long)(k0 + r) * p.va_ss; });
    const int bias_rows = p.b_sm ? min(64, R_ - r0) : 1;
    for (int i = tid; i < bias_rows * (KC / 8); i += THREADS) {
      const int r = i / (KC / 8), c = i - r * (KC / 8);
      const bool ok = k0 + c * 8 + 8 <= KEYS_PAD;
      const u16* src = p.bias + bb * p.b_sb + (long long)(r0 + r) * p.b_sm + k0 + c * 8;
      cp16(sb + OFF_BIAS + r * KC * 2 + c * 16, ok ? (const void*)src : (const void*)p.bias, ok);
    }
    cp_commit();
    cp_wait<0>();
    csync();
    if (u == (int)blockIdx.x) stamp(p, 3);
    const int mt = warp & 3, dh = warp >> 2;
    float sacc[1][KC / 8][4];
    zero<1, KC / 8>(sacc);
#pragma unroll 4
    for (int kk = 0; kk < D / 16; ++kk) mma_k16<1, KC / 8>(sacc, sq, mt * 16, D * 2, kk * 2, sk, 0, D * 2, kk * 2, lane);
    if (u == (int)blockIdx.x) stamp(p, 13);
    float mx[2] = {-1e30f, -1e30f};
#pragma unroll
    for (int nt = 0; nt < KC / 8; ++nt)
#pragma unroll
      for (int e = 0; e < 4; ++e) {
        const int row = r0 + mt * 16 + (lane >> 2) + (e >> 1) * 8;
        const int key = k0 + nt * 8 + 2 * (lane & 3) + (e & 1);
        float v = -1e30f;
        const u16* sbias = (const u16*)(smem + OFF_BIAS);
        if (key < KEYS && row < R_) v = sacc[0][nt][e] * p.scale + bf16f(sbias[(p.b_sm ? row - r0 : 0) * KC + key - k0]);
        sacc[0][nt][e] = v;
        mx[e >> 1] = fmaxf(mx[e >> 1], v);
      }
    float l[2] = {0.f, 0.f};
#pragma unroll
    for (int h = 0; h < 2; ++h) {
      mx[h] = fmaxf(mx[h], __shfl_xor_sync(0xffffffffu, mx[h], 1));
      mx[h] = fmaxf(mx[h], __shfl_xor_sync(0xffffffffu, mx[h], 2));
    }
#pragma unroll
    for (int nt = 0; nt < KC / 8; ++nt)
#pragma unroll
      for (int e = 0; e < 4; ++e) {
        const float pe = __expf(sacc[0][nt][e] - mx[e >> 1]);
        sacc[0][nt][e] = pe;
        l[e >> 1] += pe;
      }
#pragma unroll
    for (int h = 0; h < 2; ++h) {
      l[h] += __shfl_xor_sync(0xffffffffu, l[h], 1);
      l[h] += __shfl_xor_sync(0xffffffffu, l[h], 2);
    }
    if (u == (int)blockIdx.x) stamp(p, 14);
    float oacc[1][16][4];
    zero<1, 16>(oacc);
#pragma unroll
    for (int j = 0; j < KC / 16; ++j) {
      const u32 a[4] = {pack_bf16(sacc[0][2 * j][0], sacc[0][2 * j][1]), pack_bf16(sacc[0][2 * j][2], sacc[0][2 * j][3]),
                        pack_bf16(sacc[0][2 * j + 1][0], sacc[0][2 * j + 1][1]),
                        pack_bf16(sacc[0][2 * j + 1][2], sacc[0][2 * j + 1][3])};
#pragma unroll
      for (int n2 = 0; n2 < 8; ++n2) {
        u32 b[4];
        const int key = j * 16 + (lane & 7) + 8 * ((lane >> 3) & 1);
        ldsm4t(b, sv + swz(key, (dh * 128 + n2 * 16) / 8 + (lane >> 4), D * 2));
        mma(oacc[0][2 * n2], a, b[0], b[1]);
        mma(oacc[0][2 * n2 + 1], a, b[2], b[3]);
      }
    }
    if (u == (int)blockIdx.x) stamp(p, 15);
    // The unit's partial output goes out as bf16 through a padded staging tile over Q / K, so
    // every global store is a whole 16-byte chunk of a row (storing the fp32 fragments straight
    // from registers took 5 us a unit).
    const int rl = mt * 16 + (lane >> 2);
    csync();  // every warp is done with Q, K and V
#pragma unroll
    for (int nt = 0; nt < 16; ++nt) {
      const int c = dh * 128 + nt * 8 + 2 * (lane & 3);
      *(u32*)(smem + rl * (D * 2 + 16) + c * 2) = pack_bf16(oacc[0][nt][0], oacc[0][nt][1]);
      *(u32*)(smem + (rl + 8) * (D * 2 + 16) + c * 2) = pack_bf16(oacc[0][nt][2], oacc[0][nt][3]);
    }
    csync();
    u16* op = (u16*)p.apart + (long long)u * 64 * D;
    for (int i = tid; i < 64 * (D / 8); i += THREADS) {
      const int r = i / (D / 8), c = i - r * (D / 8);
      *(uint4*)(op + r * D + c * 8) = *(const uint4*)(smem + r * (D * 2 + 16) + c * 16);
    }
    if (dh == 0 && (lane & 3) == 0) {
      *(float2*)(p.aml + ((long long)u * 64 + rl) * 2) = make_float2(mx[0], l[0]);
      *(float2*)(p.aml + ((long long)u * 64 + rl + 8) * 2) = make_float2(mx[1], l[1]);
    }
    csync();
  }
  stamp(p, 4);
  grid_sync(p.bar, ++epoch * G);

  // ---------------------------------------------------------------- 3. merge the key slices
  for (int i = blockIdx.x * THREADS + tid; i < BATCH * R_ * (D / 4); i += G * THREADS) {
    const int d4 = i % (D / 4), rr = i / (D / 4), bb = rr / R_, r = rr - bb * R_;
    const int rb = r >> 6, rl = r & 63, ub = (bb * NRB + rb) * NCH;
    float2 ml[NCH];
#pragma unroll
    for (int ch = 0; ch < NCH; ++ch) {
      const float* src = p.aml + ((long long)(ub + ch) * 64 + rl) * 2;
      ml[ch] = make_float2(ldcg(src), ldcg(src + 1));
    }
    float4 v[NCH];
#pragma unroll
    for (int ch = 0; ch < NCH; ++ch) {
      uint2 w;
      asm volatile("ld.global.cg.v2.u32 {%0,%1}, [%2];" : "=r"(w.x), "=r"(w.y)
                   : "l"((const u16*)p.apart + ((long long)(ub + ch) * 64 + rl) * D + d4 * 4));
      v[ch] = make_float4(__uint_as_float(w.x << 16), __uint_as_float(w.x & 0xffff0000u),
                          __uint_as_float(w.y << 16), __uint_as_float(w.y & 0xffff0000u));
    }
    float m = -3.0e38f;
#pragma unroll
    for (int ch = 0; ch < NCH; ++ch) m = fmaxf(m, ml[ch].x);
    float ls = 0.f;
    float4 o = make_float4(0.f, 0.f, 0.f, 0.f);
#pragma unroll
    for (int ch = 0; ch < NCH; ++ch) {
      const float w = __expf(ml[ch].x - m);
      ls += w * ml[ch].y;
      o.x += w * v[ch].x; o.y += w * v[ch].y; o.z += w * v[ch].z; o.w += w * v[ch].w;
    }
    const float inv = 1.f / ls;
    *(uint2*)(p.attn + (long long)rr * D + d4 * 4) = make_uint2(pack_bf16(o.x * inv, o.y * inv), pack_bf16(o.z * inv, o.w * inv));
  }
  stamp(p, 5);
  grid_sync(p.bar, ++epoch * G);

  // ---------------------------------------------------------------- 4. o projection + residual
  for (int u = blockIdx.x; u < (W_ / 64) * (NQ * D / 256); u += G) {
    residual_unit<256, NQ * D / 256>(p, smem, ring, u, 32768, p.attn, NQ * D, 0, p.x, p.x1, p.ss_mid, &last_flag, 6);
  }
  stamp(p, 7);
  grid_sync(p.bar, ++epoch * G);

  // ---------------------------------------------------------------- 5. norm + gate/up + GeGLU
  for (int u = blockIdx.x; u < F_ / 32; u += G) {
    load_tile(sb, A_ROWS, W_, ROWS, [&](int r) { return p.x1 + (long long)r * W_; });
    cp_commit();
    rms_from_partials(p.ss_mid, p.eps, stat);
    cp_wait<0>();
    csync();
    if (u == (int)blockIdx.x) stamp(p, 8);
    const int kg = warp >> 1, ng = warp & 1;  // 4 K groups of each chunk x (gate | up) 32 columns
    float acc[4][4][4];
    zero<4, 4>(acc);
    for (int c = 0; c < GU_NKC; ++c) {
      ring.wait_full();
      const u32 w = ring.slot();
#pragma unroll
      for (int kk = kg * 2; kk < kg * 2 + 2; ++kk)
        mma_k16<4, 4, true>(acc, sb, 0, W_ * 2, (c * GU_KC + kk * 16) / 8, w, ng * 32, GU_KC * 2, kk * 2, lane);
      ring.release();
    }
    csync();
    if (u == (int)blockIdx.x) stamp(p, 9);
    float* red = (float*)smem;  // 4 k-groups x 64 x 68 floats, over the A tile (done)
    store_acc<4>(acc, red + kg * 64 * 68, 68, ng * 32, lane);
    csync();
    for (int i = tid; i < ROWS * 16; i += THREADS) {
      const int r = i >> 4, j = (i & 15) * 2;
      float g0 = 0.f, g1 = 0.f, u0 = 0.f, u1 = 0.f;
#pragma unroll
      for (int k = 0; k < 4; ++k) {
        const float* rr = red + k * 64 * 68 + r * 68;
        g0 += rr[j]; g1 += rr[j + 1]; u0 += rr[32 + j]; u1 += rr[33 + j];
      }
      float hv[2];
      const float inv = stat[r];
      const float gs[2] = {round_bf16(g0 * inv), round_bf16(g1 * inv)}, us[2] = {round_bf16(u0 * inv), round_bf16(u1 * inv)};
#pragma unroll
      for (int e = 0; e < 2; ++e) {
        const float x = gs[e];
        const float t = tanhf(0.7978845608028654f * (x + 0.044715f * x * x * x));
        hv[e] = 0.5f * x * (1.f + t) * us[e];
      }
      *(u32*)(p.h + (long long)r * F_ + u * 32 + j) = pack_bf16(hv[0], hv[1]);
    }
    csync();
  }
  stamp(p, 10);
  grid_sync(p.bar, ++epoch * G);

  // ---------------------------------------------------------------- 6. down projection + residual
  for (int u = blockIdx.x; u < (W_ / 64) * (F_ / 512); u += G) {
    residual_unit<512, F_ / 512>(p, smem, ring, u, 65536, p.h, F_, W_ / 64, p.x1, p.out, p.ss_out, &last_flag, 11);
  }
  stamp(p, 12);

  // Reset the barrier for the next launch once every CTA is past the last grid barrier.
  csync();
  if (tid == 0) {
    __threadfence();
    if (atomicAdd(p.bar + 1, 1u) == (u32)G - 1) {
      p.bar[0] = 0;
      p.bar[1] = 0;
      __threadfence();
    }
  }
}
