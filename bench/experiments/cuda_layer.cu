// One persistent CUDA C++ kernel per action-expert decoder layer-step (pi0's Gemma-300M expert).
//
// Compiled at run time by NVRTC (bench/experiments/cuda_layer.py) with the dimensions as macros:
//   W_ width, F_ MLP hidden, NQ query heads (one KV head), D head dim, SEQ tokens, BATCH batch,
//   ROWS = BATCH * SEQ rows (<= 64), KEYS keys in the cache.
// One CTA per SM (256 threads, ~225 KB of shared memory), five grid barriers:
//   1. RMSNorm (in shared memory) + QKV GEMM, RoPE on interleaved pairs, q to scratch,
//      k / v into the KV cache;
//   2. split-KV attention: (row block of 64 folded query rows) x (48 keys) units;
//   3. merge of the key slices (element-parallel over the whole grid);
//   4. o projection, split-K over heads; the last CTA of a column tile adds the residual;
//   5. RMSNorm + gate/up GEMM (weights streamed through a 6-stage ring), GeGLU;
//   6. down projection like 4.
// Every A operand is loaded once per unit into shared memory and read by ldmatrix; weights
// stream through cp.async.cg (L2 only, no L1 allocation), bf16 mma.sync m16n8k16, fp32 sums.

typedef unsigned int u32;
typedef unsigned short u16;

#define THREADS 256
#define NQKV ((NQ + 2) * D)
#define OFF_W 131072
#define OFF_STAT 229376
#define SMEM_BYTES (OFF_STAT + 512)
#define R_ (SEQ * NQ)                 /* folded query rows per batch element */
#define NRB ((R_ + 63) / 64)
#define KC 48
#define NCH ((KEYS + KC - 1) / KC)
#define GU_STAGES 6
#define GU_KC 128
#define GU_NKC (W_ / GU_KC)
#define OFF_BIAS 81920              /* attention: 64 x KC bias tile, after Q / K / V */
#define OFF_OW 90112                /* o weights, prefetched while attention runs */
#define KEYS_PAD (((KEYS + 15) / 16) * 16)

struct Params {
  const u16* x; const u16* wqkv; const u16* g1; const float* cos; const float* sin;
  u16* q; u16* k_out; u16* v_out; const u16* k_all; const u16* v_all; const u16* bias;
  float* apart; float* aml; u16* attn;
  const u16* wo; float* part; u16* x1; const u16* g2; const u16* wgu; u16* h; const u16* wd; u16* out;
  int* cnt; u32* bar; long long* stamps;
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
__device__ __forceinline__ float4 ldcg4(const float* p) {
  float4 v;
  asm volatile("ld.global.cg.v4.f32 {%0,%1,%2,%3}, [%4];" : "=f"(v.x), "=f"(v.y), "=f"(v.z), "=f"(v.w) : "l"(p));
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
template <int MT, int NT>
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
    ldsm4(b, b_base + swz(row, b_chunk + ((lane >> 3) & 1), b_rowbytes));
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

// RMSNorm of the ROWS rows of a W_-wide swizzled bf16 tile, in place: x * rsqrt(mean(x^2) + eps) * g.
__device__ void rms_norm_tile(unsigned char* tile, const u16* g, float eps, float* stat) {
  const int lane = threadIdx.x & 31, warp = threadIdx.x >> 5;
  for (int r = warp; r < ROWS; r += THREADS / 32) {
    float ss = 0.f;
    for (int c = lane; c < W_ / 8; c += 32) {
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
  __syncthreads();
  static_assert(THREADS % (W_ / 8) == 0, "each thread keeps one chunk of the norm weight");
  const uint4 gw = *(const uint4*)(g + (threadIdx.x % (W_ / 8)) * 8);
  const u32 g4[4] = {gw.x, gw.y, gw.z, gw.w};
  for (int i = threadIdx.x; i < ROWS * (W_ / 8); i += THREADS) {
    const int r = i / (W_ / 8), c = i - r * (W_ / 8);  // logical chunk c of row r
    uint4* ptr = (uint4*)(tile + swz(r, c, W_ * 2));
    const uint4 v = *ptr;
    const u32 w4[4] = {v.x, v.y, v.z, v.w};
    u32 o4[4];
    const float inv = stat[r];
#pragma unroll
    for (int e = 0; e < 4; ++e) {
      const float lo = __uint_as_float(w4[e] << 16) * inv * __uint_as_float(g4[e] << 16);
      const float hi = __uint_as_float(w4[e] & 0xffff0000u) * inv * __uint_as_float(g4[e] & 0xffff0000u);
      o4[e] = pack_bf16(lo, hi);
    }
    *ptr = make_uint4(o4[0], o4[1], o4[2], o4[3]);
  }
  __syncthreads();
}

__device__ __forceinline__ void grid_sync(u32* bar, u32 target) {
  __syncthreads();
  if (threadIdx.x == 0) {
    __threadfence();
    asm volatile("red.release.gpu.global.add.u32 [%0], 1;" :: "l"(bar) : "memory");
    u32 v;
    do {
      asm volatile("ld.acquire.gpu.global.u32 %0, [%1];" : "=r"(v) : "l"(bar) : "memory");
    } while (v < target);
    __threadfence();
  }
  __syncthreads();
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
__device__ void splitk_finish(const Params& p, const float* red, int nt, int ks, int cnt_idx,
                              const u16* residual, u16* out, int* last_flag) {
  float* mine = p.part + (long long)(ks * (W_ / 64) + nt) * 64 * 64;
  for (int i = threadIdx.x; i < ROWS * 16; i += THREADS) {
    const int r = i >> 4, c = (i & 15) * 4;
    const float* a = red + r * 68 + c;
    const float* b = red + 64 * 68 + r * 68 + c;
    *(float4*)(mine + r * 64 + c) = make_float4(a[0] + b[0], a[1] + b[1], a[2] + b[2], a[3] + b[3]);
  }
  __threadfence();
  __syncthreads();
  if (threadIdx.x == 0) *last_flag = atomicAdd(p.cnt + cnt_idx, 1) == SPLITS - 1;
  __syncthreads();
  if (*last_flag) {
    __threadfence();
    for (int i = threadIdx.x; i < ROWS * 16; i += THREADS) {
      const int r = i >> 4, c = (i & 15) * 4;
      float4 v[SPLITS];
#pragma unroll
      for (int s = 0; s < SPLITS; ++s) v[s] = ldcg4(p.part + (long long)(s * (W_ / 64) + nt) * 64 * 64 + r * 64 + c);
      uint2 res;
      asm volatile("ld.global.cg.v2.u32 {%0,%1}, [%2];" : "=r"(res.x), "=r"(res.y) : "l"(residual + r * W_ + nt * 64 + c));
      float o0 = __uint_as_float(res.x << 16), o1 = __uint_as_float(res.x & 0xffff0000u);
      float o2 = __uint_as_float(res.y << 16), o3 = __uint_as_float(res.y & 0xffff0000u);
      float s0 = 0.f, s1 = 0.f, s2 = 0.f, s3 = 0.f;
#pragma unroll
      for (int s = 0; s < SPLITS; ++s) { s0 += v[s].x; s1 += v[s].y; s2 += v[s].z; s3 += v[s].w; }
      *(uint2*)(out + r * W_ + nt * 64 + c) = make_uint2(pack_bf16(s0 + o0, s1 + o1), pack_bf16(s2 + o2, s3 + o3));
    }
    if (threadIdx.x == 0) p.cnt[cnt_idx] = 0;
  }
  __syncthreads();
}

// One unit of a split-K projection that adds the residual (o: KU = 256 of the 2048 attention
// columns; down: KU = 512 of the 4096 MLP columns). The weights are already requested at w_off.
template <int KU, int SPLITS>
__device__ __forceinline__ void residual_unit(const Params& p, unsigned char* smem, int u, u32 w_off, u32 red_off,
                                              const u16* a, int lda, int cnt_base, const u16* residual, u16* out,
                                              int* last_flag, int stamp_idx) {
  const u32 sb = smem_addr(smem);
  const int lane = threadIdx.x & 31, warp = threadIdx.x >> 5;
  const int nt = u % (W_ / 64), ks = u / (W_ / 64);
  load_tile(sb, 64, KU, ROWS, [&](int r) { return a + (long long)r * lda + ks * KU; });
  cp_commit();
  cp_wait<0>();
  __syncthreads();
  if (u == (int)blockIdx.x) stamp(p, stamp_idx);
  const int kg = warp >> 2, ng = warp & 3;  // 2 K halves x 4 column groups of 16
  float acc[4][2][4];
  zero<4, 2>(acc);
#pragma unroll 4
  for (int kk = 0; kk < KU / 32; ++kk) {
    const int chunk = (kg * (KU / 32) + kk) * 2;
    mma_k16<4, 2>(acc, sb, 0, KU * 2, chunk, sb + w_off, ng * 16, KU * 2, chunk, lane);
  }
  float* red = (float*)(smem + red_off);
  store_acc<2>(acc, red + kg * 64 * 68, 68, ng * 16, lane);
  __syncthreads();
  splitk_finish<SPLITS>(p, red, nt, ks, cnt_base + nt, residual, out, last_flag);
}

// Weight tiles do not depend on any phase, so a CTA issues the next phases' weights as soon as
// the shared memory they land in is free, before it waits at a grid barrier.
__device__ __forceinline__ void issue_o_weights(const Params& p, u32 sb, int u) {
  const int nt = u % (W_ / 64), ks = u / (W_ / 64);
  load_tile(sb + OFF_OW, 64, 256, 64, [&](int r) { return p.wo + (long long)(nt * 64 + r) * NQ * D + ks * 256; });
}
__device__ __forceinline__ void issue_gu_chunk(const Params& p, u32 sb, int u, int c) {
  load_tile(sb + OFF_W + (c % GU_STAGES) * 16384, 64, GU_KC, 64, [&](int r) {
    const long long row = r < 32 ? u * 32 + r : F_ + u * 32 + r - 32;
    return p.wgu + row * W_ + c * GU_KC;
  });
}
__device__ __forceinline__ void issue_down_weights(const Params& p, u32 sb, int u) {
  const int nt = u % (W_ / 64), ks = u / (W_ / 64);
  load_tile(sb + OFF_W, 64, 512, 64, [&](int r) { return p.wd + (long long)(nt * 64 + r) * F_ + ks * 512; });
}

extern "C" __global__ void __launch_bounds__(THREADS, 1) layer_step(const Params p) {
  extern __shared__ __align__(1024) unsigned char smem[];
  const u32 sb = smem_addr(smem);
  const int tid = threadIdx.x, lane = tid & 31, warp = tid >> 5;
  const int G = gridDim.x;
  float* stat = (float*)(smem + OFF_STAT);
  __shared__ int last_flag;
  u32 epoch = 0;
  stamp(p, 0);

  // ---------------------------------------------------------------- 1. norm + QKV + RoPE
  for (int u = blockIdx.x; u < NQKV / 32; u += G) {
    load_tile(sb + OFF_W, 32, W_, 32, [&](int r) { return p.wqkv + (long long)(u * 32 + r) * W_; });
    load_tile(sb, 64, W_, ROWS, [&](int r) { return p.x + (long long)r * W_; });
    cp_commit();
    cp_wait<0>();
    __syncthreads();
    if (u == (int)blockIdx.x) stamp(p, 1);
    rms_norm_tile(smem, p.g1, p.eps, stat);
    float acc[4][4][4];
    zero<4, 4>(acc);
#pragma unroll
    for (int ks = 0; ks < W_ / 16 / 8; ++ks) {  // warp w: K slice [w * W_/8, (w+1) * W_/8)
      const int chunk = (warp * (W_ / 8) + ks * 16) / 8;
      mma_k16<4, 4>(acc, sb, 0, W_ * 2, chunk, sb + OFF_W, 0, W_ * 2, chunk, lane);
    }
    __syncthreads();
    float* red = (float*)(smem + OFF_W);  // 8 warps x 64 x 36 floats = 73.7 KB, over W (done)
    store_acc<4>(acc, red + warp * 64 * 36, 36, 0, lane);
    __syncthreads();
    for (int i = tid; i < ROWS * 16; i += THREADS) {
      const int r = i >> 4, c = (i & 15) * 2;
      float a0 = 0.f, a1 = 0.f;
#pragma unroll
      for (int w = 0; w < 8; ++w) {
        a0 += red[w * 64 * 36 + r * 36 + c];
        a1 += red[w * 64 * 36 + r * 36 + c + 1];
      }
      a0 = round_bf16(a0);
      a1 = round_bf16(a1);
      const int n = u * 32 + c, bb = r / SEQ, s = r - bb * SEQ;
      if (n < NQ * D + D) {
        const int dd = n % D, j = dd >> 1;
        const float cs = p.cos[bb * p.cos_sb + s * p.cos_ss + j], sn = p.sin[bb * p.cos_sb + s * p.cos_ss + j];
        const u32 v = pack_bf16(a0 * cs - a1 * sn, a0 * sn + a1 * cs);
        if (n < NQ * D) *(u32*)(p.q + (long long)r * NQ * D + n) = v;
        else *(u32*)(p.k_out + bb * p.k_sb + s * p.k_ss + dd) = v;
      } else {
        *(u32*)(p.v_out + bb * p.v_sb + s * p.v_ss + (n - NQ * D - D)) = pack_bf16(a0, a1);
      }
    }
    __syncthreads();
  }
  if ((int)blockIdx.x < (W_ / 64) * (NQ * D / 256)) {
    issue_o_weights(p, sb, blockIdx.x);
    cp_commit();
  }
  if ((int)blockIdx.x < F_ / 32)
    for (int c = 0; c < GU_STAGES && c < GU_NKC; ++c) {
      issue_gu_chunk(p, sb, blockIdx.x, c);
      cp_commit();
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
    __syncthreads();
    if (u == (int)blockIdx.x) stamp(p, 3);
    const int mt = warp & 3, dh = warp >> 2;
    float sacc[1][KC / 8][4];
    zero<1, KC / 8>(sacc);
#pragma unroll 4
    for (int kk = 0; kk < D / 16; ++kk) mma_k16<1, KC / 8>(sacc, sq, mt * 16, D * 2, kk * 2, sk, 0, D * 2, kk * 2, lane);
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
    float* op = p.apart + (long long)u * 64 * D;
    const int rl = mt * 16 + (lane >> 2);
#pragma unroll
    for (int nt = 0; nt < 16; ++nt) {
      const int c = dh * 128 + nt * 8 + 2 * (lane & 3);
      *(float2*)(op + rl * D + c) = make_float2(oacc[0][nt][0], oacc[0][nt][1]);
      *(float2*)(op + (rl + 8) * D + c) = make_float2(oacc[0][nt][2], oacc[0][nt][3]);
    }
    if (dh == 0 && (lane & 3) == 0) {
      *(float2*)(p.aml + ((long long)u * 64 + rl) * 2) = make_float2(mx[0], l[0]);
      *(float2*)(p.aml + ((long long)u * 64 + rl + 8) * 2) = make_float2(mx[1], l[1]);
    }
    __syncthreads();
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
    for (int ch = 0; ch < NCH; ++ch) v[ch] = ldcg4(p.apart + ((long long)(ub + ch) * 64 + rl) * D + d4 * 4);
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
    if (u != (int)blockIdx.x) issue_o_weights(p, sb, u);
    residual_unit<256, NQ * D / 256>(p, smem, u, OFF_OW, 32768, p.attn, NQ * D, 0, p.x, p.x1, &last_flag, 6);
  }
  stamp(p, 7);
  grid_sync(p.bar, ++epoch * G);

  // ---------------------------------------------------------------- 5. norm + gate/up + GeGLU
  for (int u = blockIdx.x; u < F_ / 32; u += G) {
    auto issue = [&](int c) {
      issue_gu_chunk(p, sb, u, c);
      cp_commit();
    };
    if (u != (int)blockIdx.x)
      for (int c = 0; c < GU_STAGES && c < GU_NKC; ++c) issue(c);
    load_tile(sb, 64, W_, ROWS, [&](int r) { return p.x1 + (long long)r * W_; });
    cp_commit();
    cp_wait<0>();
    __syncthreads();
    if (u == (int)blockIdx.x) stamp(p, 8);
    rms_norm_tile(smem, p.g2, p.eps, stat);
    const int kg = warp >> 1, ng = warp & 1;
    float acc[4][4][4];
    zero<4, 4>(acc);
    for (int c = 0; c < GU_NKC; ++c) {
      if (c >= GU_STAGES) {
        if (c == GU_NKC - 1) cp_wait<0>();
        else cp_wait<1>();
        __syncthreads();
      }
      const u32 stage = sb + OFF_W + (c % GU_STAGES) * 16384;
#pragma unroll
      for (int kk = kg * 2; kk < kg * 2 + 2; ++kk)
        mma_k16<4, 4>(acc, sb, 0, W_ * 2, (c * GU_KC + kk * 16) / 8, stage, ng * 32, GU_KC * 2, kk * 2, lane);
      if (c + GU_STAGES < GU_NKC) {
        __syncthreads();
        issue(c + GU_STAGES);
      }
    }
    __syncthreads();
    if (u == (int)blockIdx.x) stamp(p, 9);
    float* red = (float*)smem;  // 4 k-groups x 64 x 68 floats, over the A tile (done)
    store_acc<4>(acc, red + kg * 64 * 68, 68, ng * 32, lane);
    __syncthreads();
    for (int i = tid; i < ROWS * 16; i += THREADS) {
      const int r = i >> 4, j = (i & 15) * 2;
      float g0 = 0.f, g1 = 0.f, u0 = 0.f, u1 = 0.f;
#pragma unroll
      for (int k = 0; k < 4; ++k) {
        const float* rr = red + k * 64 * 68 + r * 68;
        g0 += rr[j]; g1 += rr[j + 1]; u0 += rr[32 + j]; u1 += rr[33 + j];
      }
      float hv[2];
      const float gs[2] = {round_bf16(g0), round_bf16(g1)}, us[2] = {round_bf16(u0), round_bf16(u1)};
#pragma unroll
      for (int e = 0; e < 2; ++e) {
        const float x = gs[e];
        const float t = tanhf(0.7978845608028654f * (x + 0.044715f * x * x * x));
        hv[e] = 0.5f * x * (1.f + t) * us[e];
      }
      *(u32*)(p.h + (long long)r * F_ + u * 32 + j) = pack_bf16(hv[0], hv[1]);
    }
    __syncthreads();
  }
  if ((int)blockIdx.x < (W_ / 64) * (F_ / 512)) {
    issue_down_weights(p, sb, blockIdx.x);
    cp_commit();
  }
  stamp(p, 10);
  grid_sync(p.bar, ++epoch * G);

  // ---------------------------------------------------------------- 6. down projection + residual
  for (int u = blockIdx.x; u < (W_ / 64) * (F_ / 512); u += G) {
    if (u != (int)blockIdx.x) issue_down_weights(p, sb, u);
    residual_unit<512, F_ / 512>(p, smem, u, OFF_W, 65536, p.h, F_, W_ / 64, p.x1, p.out, &last_flag, 11);
  }
  stamp(p, 12);

  // Reset the barrier for the next launch once every CTA is past the last grid barrier.
  __syncthreads();
  if (tid == 0) {
    __threadfence();
    if (atomicAdd(p.bar + 1, 1u) == (u32)G - 1) {
      p.bar[0] = 0;
      p.bar[1] = 0;
      __threadfence();
    }
  }
}
