// Scratch buffers reused across calls. The filter's full-resolution scratch (the root manifold
// alone is D x H x W) is touched a few times per call; on a fresh allocation the page faults cost
// about as much as the filtering itself, so released buffers are kept (up to kMaxCachedBytes) and
// handed to the next call of any size that fits.
#pragma once

#include <algorithm>
#include <cstddef>
#include <cstdint>
#include <memory>
#include <mutex>
#include <utility>
#include <vector>

namespace torchmanifold {
namespace cpu {

class BufferPool {
 public:
  // 1 GiB: about every scratch buffer of one 4K frame (8.3 MP, float32, 17 guide channels, height 3:
  // the 7 nodes' weights alone are 7 x 33 MB, a sanitised guide 560 MB); a larger call allocates
  // afresh rather than pinning more memory for the life of the process.
  static constexpr size_t kMaxCachedBytes = size_t(1) << 30;
  using Block = std::pair<size_t, std::unique_ptr<unsigned char[]>>;

  static BufferPool& instance() {
    static BufferPool pool;
    return pool;
  }

  // Smallest cached block of at least `bytes`, else a new one; contents are undefined.
  Block acquire(size_t bytes) {
    {
      std::lock_guard<std::mutex> lock(mu_);
      auto best = free_.end();
      for (auto it = free_.begin(); it != free_.end(); ++it)
        if (it->first >= bytes && (best == free_.end() || it->first < best->first)) best = it;
      if (best != free_.end()) {
        Block b = std::move(*best);
        free_.erase(best);
        cached_ -= b.first;
        return b;
      }
    }
    return Block(bytes, std::unique_ptr<unsigned char[]>(new unsigned char[std::max<size_t>(bytes, 1)]));
  }

  void release(Block b) {
    if (!b.second) return;
    std::lock_guard<std::mutex> lock(mu_);
    // Over the cap: drop the smallest cached blocks first, never more than needed.
    while (cached_ + b.first > kMaxCachedBytes && !free_.empty()) {
      auto smallest = std::min_element(free_.begin(), free_.end(),
                                       [](const Block& x, const Block& y) { return x.first < y.first; });
      cached_ -= smallest->first;
      free_.erase(smallest);
    }
    if (cached_ + b.first > kMaxCachedBytes) return;
    cached_ += b.first;
    free_.push_back(std::move(b));
  }

 private:
  std::mutex mu_;
  std::vector<Block> free_;
  size_t cached_ = 0;
};

// A typed view of a pooled block: resize() keeps nothing, contents start undefined.
template <typename X>
class Scratch {
 public:
  Scratch() = default;
  Scratch(const Scratch&) = delete;
  Scratch& operator=(const Scratch&) = delete;
  Scratch(Scratch&& o) noexcept : block_(std::move(o.block_)), n_(o.n_) { o.n_ = 0; }
  Scratch& operator=(Scratch&& o) noexcept {
    if (this != &o) {
      BufferPool::instance().release(std::move(block_));
      block_ = std::move(o.block_);
      n_ = o.n_;
      o.n_ = 0;
    }
    return *this;
  }
  ~Scratch() { BufferPool::instance().release(std::move(block_)); }

  void resize(int64_t n) {
    const size_t bytes = static_cast<size_t>(n) * sizeof(X);
    if (!block_.second || block_.first < bytes) {
      BufferPool::instance().release(std::move(block_));
      block_ = BufferPool::instance().acquire(bytes);
    }
    n_ = n;
  }
  void assign(int64_t n, X value) {
    resize(n);
    std::fill(begin(), end(), value);
  }
  X* data() { return reinterpret_cast<X*>(block_.second.get()); }
  const X* data() const { return reinterpret_cast<const X*>(block_.second.get()); }
  X* begin() { return data(); }
  X* end() { return data() + n_; }
  X& operator[](int64_t i) { return data()[i]; }
  const X& operator[](int64_t i) const { return data()[i]; }
  int64_t size() const { return n_; }

 private:
  BufferPool::Block block_;
  int64_t n_ = 0;
};

}  // namespace cpu
}  // namespace torchmanifold
